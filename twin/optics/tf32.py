"""torch's TF32 switch for CUDA matrix products, set for a block and restored after it (also on an exception).

Shared by twin.optics.forward.project (the projection GEMM) and reconstruction.network.split_tf32_linear (the
decoder's split-precision products). On the CPU the flag changes nothing. The flag is process-wide, not per thread:
a matrix product another thread runs inside the block sees it too.
"""
from __future__ import annotations

from contextlib import contextmanager


@contextmanager
def tf32_matmul(enabled: bool):
    """torch.backends.cuda.matmul.allow_tf32 = enabled inside the block, the caller's value after it."""
    import torch

    flags = torch.backends.cuda.matmul
    before = flags.allow_tf32
    flags.allow_tf32 = bool(enabled)
    try:
        yield
    finally:
        flags.allow_tf32 = before

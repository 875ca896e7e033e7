"""Training across processes (docs/scale-out.md): `hemicube train` under torchrun, one process per GPU (NCCL) or per
CPU worker (gloo), through torch.distributed's DistributedDataParallel.

    torchrun --nproc_per_node=2 -m hemicube.cli train --rig mini --device cpu -o runs/ddp   # gloo, 2 CPU workers
    torchrun --nproc_per_node=N -m hemicube.cli train --rig paper --device cuda -o runs/p   # NCCL, N GPUs

What makes N processes train the network one process would (same global batch, docs/scale-out.md):
* data: every rank draws the parameters of the whole global batch i from the batch's counter-based seed
  (reconstruction.network.data) and renders only its own contiguous slice of it, so the ranks' samples never overlap
  and their union is exactly the single-process batch;
* batch statistics: the encoder's BatchNorm layers use the statistics of the global batch
  (`GlobalBatchNorm1d`), as they would in one process;
* gradients: DDP averages them over the ranks, and the loss is each rank's mean over an equal slice, so the
  update is the gradient of the global batch's mean loss;
* what stays per rank: the dropout masks and the 5% measurement noise (paper §6) come from each rank's own
  torch RNG, seeded per rank; they are independent draws, not the single-process ones.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import nn

__all__ = ["Dist", "join", "GlobalBatchNorm1d", "globalise_batchnorm", "all_sum", "any_rank", "gather_objects",
           "barrier"]


@dataclass(frozen=True)
class Dist:
    """This process's place in the run: rank of world, and the device it trains on."""
    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")
    backend: str | None = None

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def active(self) -> bool:
        return self.world > 1


def join(device: str) -> Dist:
    """The process group torchrun describes in the environment (WORLD_SIZE, RANK, LOCAL_RANK, MASTER_ADDR,
    MASTER_PORT), joined; a lone process (no WORLD_SIZE, or 1) joins nothing. Under torchrun a bare "cuda"
    device means this process's GPU, cuda:LOCAL_RANK; NCCL on GPUs, gloo on CPUs."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    dev = torch.device(device)
    if world <= 1:
        return Dist(device=dev)
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if dev.type == "cuda":
        if dev.index is None:
            dev = torch.device("cuda", local)
        torch.cuda.set_device(dev)
        backend = "nccl"
    else:
        backend = "gloo"
    if not dist.is_initialized():
        dist.init_process_group(backend, device_id=dev if dev.type == "cuda" else None)
    return Dist(rank=rank, world=world, device=dev, backend=backend)


class GlobalBatchNorm1d(nn.BatchNorm1d):
    """BatchNorm1d whose training statistics are those of the global batch over every rank, with gradients
    through them: what nn.SyncBatchNorm does, on any backend (torch's SyncBatchNorm refuses CPU tensors, so
    it cannot run the gloo training that CI checks). Mean and variance are two all-reduces (two-pass
    variance, as in one process); the running statistics get the same update on every rank. Alone, or in
    eval mode, it is BatchNorm1d."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (self.training and dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(x)
        counted = _all_reduce(torch.cat([x.sum(0), x.new_tensor([x.shape[0]])]))
        n = counted[-1]
        mean = counted[:-1] / n
        centred = x - mean
        var = _all_reduce(centred.square().sum(0)) / n
        y = centred * torch.rsqrt(var + self.eps)
        if self.affine:
            y = y * self.weight + self.bias
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked += 1
                f = (1.0 / float(self.num_batches_tracked)) if self.momentum is None else self.momentum
                self.running_mean.mul_(1 - f).add_(mean.detach(), alpha=f)
                self.running_var.mul_(1 - f).add_(var.detach() * (n / (n - 1)), alpha=f)  # unbiased, as torch
        return y


def _all_reduce(t: torch.Tensor) -> torch.Tensor:
    """The sum over ranks, differentiable (its backward all-reduces the gradient). torch 2.13 marks
    torch.distributed.nn.functional deprecated in favour of the functional collectives, which carry gradients
    through all-gather, reduce-scatter and all-to-all but not all-reduce; this one does."""
    import warnings

    from torch.distributed.nn.functional import all_reduce

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        return all_reduce(t)


def globalise_batchnorm(module: nn.Module) -> nn.Module:
    """`module` with every BatchNorm1d replaced by a GlobalBatchNorm1d holding the same parameters and
    statistics (the state dict's keys do not change, so checkpoints move between world sizes)."""
    for name, child in module.named_children():
        if type(child) is nn.BatchNorm1d:
            g = GlobalBatchNorm1d(child.num_features, child.eps, child.momentum, child.affine,
                                  child.track_running_stats, device=child.running_mean.device)
            g.load_state_dict(child.state_dict())
            setattr(module, name, g)
        else:
            globalise_batchnorm(child)
    return module


def all_sum(values: torch.Tensor, ctx: Dist) -> torch.Tensor:
    """The sum over ranks (a copy; the input alone when the run has one process)."""
    if not ctx.active:
        return values
    out = values.clone()
    dist.all_reduce(out)
    return out


def any_rank(flag: bool, ctx: Dist) -> bool:
    """True on every rank when any rank says True (all ranks must call it at the same point)."""
    if not ctx.active:
        return flag
    return bool(all_sum(torch.tensor([1.0 if flag else 0.0], device=ctx.device), ctx).item() > 0)


def gather_objects(obj, ctx: Dist) -> list:
    """Every rank's `obj`, in rank order, on every rank."""
    if not ctx.active:
        return [obj]
    out = [None] * ctx.world
    dist.all_gather_object(out, obj)
    return out


def barrier(ctx: Dist) -> None:
    if ctx.active:
        dist.barrier()

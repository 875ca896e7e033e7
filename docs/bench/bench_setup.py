"""What the record scripts in docs/bench share (imported by them: they run as `python docs/bench/X.py`, so this
folder is on sys.path): the synthetic fine-tuning texels, timed fine-tuning steps, and a registry of synchronised
function timers."""
import time
from collections import defaultdict

import numpy as np
import torch

import twin
from reconstruction.bench import _texels
from reconstruction.latents import decode
from reconstruction.pipeline import load_network


def finetune_texels(rig_name: str, n: int, dev: str):
    """`hemicube bench reconstruct`'s n synthetic texels (seed 0) on rig `rig_name` with the shipped network, the
    lines with 1% multiplicative noise (the extracted photos' level), their decoded latents, line 0 held out.
    Returns (rig, model, lines, W, z, hold)."""
    torch.manual_seed(0)
    rig = twin.load_rig(rig_name)
    model = load_network("pretrained", rig, dev)
    learned, lines, pos, W, _ = _texels(rig, model, n, 0, dev, exact=False)
    rng = np.random.default_rng(1)
    lines = (lines * (1 + 0.01 * rng.standard_normal(lines.shape))).astype(np.float32)
    return rig, model, lines, W, decode(model, learned, device=dev), (0,)


def adam_step_ms(energy, x0: torch.Tensor, count: int = 30, warmup: int = 3) -> float:
    """Milliseconds a fine-tuning step (energy, backward, Adam at lr 0.02) from x0 takes, over `count` steps after
    `warmup` untimed ones, synchronised on x0's device."""
    sync = torch.cuda.synchronize if x0.is_cuda else (lambda: None)
    x = x0.clone().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=0.02)
    for i in range(count + warmup):
        if i == warmup:
            sync()
            t = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        e = energy(x)
        e.backward()
        opt.step()
        float(e.detach())
    sync()
    return (time.perf_counter() - t) / count * 1e3


def timers():
    """(stats, timed): stats[name] = [calls, seconds, count]; timed(name, fn, count=None) wraps fn with a timer
    that synchronises the GPU around each call and adds count(*args) to the name's count."""
    stats = defaultdict(lambda: [0, 0.0, 0])
    sync = torch.cuda.synchronize if torch.cuda.is_available() else (lambda: None)

    def timed(name, fn, count=None):
        def wrapper(*a, **k):
            sync()
            t0 = time.perf_counter()
            r = fn(*a, **k)
            sync()
            s = stats[name]
            s[0] += 1
            s[1] += time.perf_counter() - t0
            if count is not None:
                s[2] += count(*a)
            return r
        return wrapper

    return stats, timed

"""Training loop of the acquisition network (paper §6): synthetic lumitexels in, learned patterns out.

    cfg = TrainConfig(rig="mini", steps=2000)
    metrics = train(cfg, "runs/mini")        # resumable; re-run to continue from the last checkpoint

A run folder holds
    metrics.jsonl            one JSON object per evaluation (step, train_loss, train_swap_loss,
                             heldout_loss, wall_s, lumitexels_per_s), appended and flushed line by line
    checkpoint-STEP-SAVE-K.safetensors
                             model state ("model.<name>") + Adam state ("optim.<param index>.<key>"), in shard
                             files of at most CHECKPOINT_SHARD_BYTES of tensor data each (a larger tensor is cut
                             into pieces "<name>@k" along its flattened elements)
    checkpoint.json          step, config, rig digest, RNG states (lists), wall time, the shard files and their
                             sha256; written LAST, so a checkpoint is valid only when its JSON names it (every
                             shard's sha256 must match); each save writes new shard names and removes the
                             files no checkpoint names only after its JSON is in place, so a run killed at any
                             point keeps a valid checkpoint
    patterns.npz             the learned patterns as a twin.capture.patterns file: 64 frames (32 signed pairs,
                             "learned_00+", "learned_00-", ...) x ALL rig LEDs (bottom LEDs 0) x 3 equal
                             channels; usable as `hemicube capture --patterns`
    loss.png                 train and held-out loss vs step
    metrics.json             summary (final held-out loss, steps, wall time, iterations/s, lumitexels/s,
                             command line, whether the invocation stopped on its time limit)

Chunks. `train(..., time_limit=S)` (`hemicube train --time-limit S`) stops once S seconds have passed since
the call began, after the step in hand: it evaluates the held-out set there (one extra metrics row), writes
a checkpoint and the outputs, and returns with "stopped_on_time_limit": true. Re-running the same command
resumes. This exists for machines lent in slices of a few minutes (the paper rig's GPU training); the
limit is not part of the config (a chunk's length does not change the trained model), and at least one
step runs per call, so repeated calls always progress. The final checkpoint save (78 MB for the shipped compact
paper-rig network, about 2 GB for the released architecture) comes after the limit: leave a margin for it.
The shards let a chunk's checkpoint leave the machine it ran on: checkpoints in files of at most 16 MiB, the
largest file a lent GPU machine gives back, so that the next chunk can run on another machine.

Steps. Step i (0-based) trains on batch i of the data stream, so a resumed run sees exactly the data of an
uninterrupted one; the global torch RNG (dropout, measurement noise) is saved in the checkpoint and
restored, so a resumed run reproduces an uninterrupted one bit for bit (CPU, one thread). A fraction
`pair_fraction` of the steps, evenly spaced (step i is a pair step when floor((i+1) f) > floor(i f)), are
albedo-swap steps: `albedo_swap_loss` on `pair_batch(i)`; the others use `lumitexel_loss` (Eq. 3) on
`batch(i)` with target views[:, 0].

Losses reported. heldout_loss: Eq. 3 (sum over LEDs, mean over texels) on a fixed held-out set, in eval
mode. train_loss: the mean Eq. 3 per lumitexel over the steps since the last evaluation (a pair step's
swap loss, a sum over 4 lumitexels, counts divided by 4, so the number is comparable with heldout_loss);
train_swap_loss: the raw mean albedo_swap_loss of the pair steps. lumitexels_per_s: network input samples
(B per plain step, 2B per pair step) per second of wall time, data synthesis included.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from twin.atomic import atomic_path, file_sha256, write_bytes_atomic
from twin.capture.plan import DEFAULT_SEED
from twin.outputs import claim_output

from reconstruction.network.run_folder import CHECKPOINT_JSON, RUN_FOLDER
from reconstruction.network.data import LumitexelStream, SamplingConfig, heldout_set, led_directions, stream_seed
from reconstruction.network.distributed import Dist, any_rank, all_sum, barrier, gather_objects, globalise_batchnorm, join
from reconstruction.network.architecture import AcquisitionNet, NetworkConfig, albedo_swap_loss, lumitexel_loss

__all__ = ["TrainConfig", "TrainError", "train", "is_pair_step", "export_patterns", "load_checkpoint",
           "CHECKPOINT_SHARD_BYTES", "CHECKPOINT_JSON", "heldout_losses", "blind_loss", "read_metrics"]

_SHARD_PREFIX, _LEGACY_TENSORS = "checkpoint-", "checkpoint.safetensors"  # a shard's name; version 1's one file
# tensor bytes per shard file: 15 MiB, so that a file with its safetensors header stays under 16 MiB (module docstring)
CHECKPOINT_SHARD_BYTES = 15 * 2 ** 20
# config fields that may change between a run and its resumption: they do not change the trained model
# (steps: how far to go; eval/checkpoint cadence: what is written along the way; device: where it runs)
RESUMABLE_FIELDS = ("steps", "eval_every", "checkpoint_every", "device")


class TrainError(ValueError):
    """A run folder that cannot be (re)used: a different config, a corrupt checkpoint."""


@dataclass(frozen=True)
class TrainConfig:
    # rig: a built-in name ("mini", "paper") or a rig folder (twin.load_rig)
    rig: str = "mini"
    # steps: this project's CPU default for the mini rig (the paper does not state its iteration count)
    steps: int = 2000
    # batch: paper §6 uses 50; 256 is this project's default for the CPU mini rig (a 260 k-parameter net
    # is cheap per sample, larger batches use the core better and give smoother gradients)
    batch: int = 256
    # lr: paper §6 uses Adam with 1e-4; 1e-3 is this project's default for the small mini-rig network,
    # which converges too slowly at 1e-4 in a CPU budget of a few thousand steps. Adam beta1 = 0.9 (paper).
    lr: float = 1e-3
    beta1: float = 0.9
    beta2: float = 0.999  # PyTorch's default (the paper gives only beta1)
    seed: int = DEFAULT_SEED  # every command's --seed default; the shipped networks were trained with 0 (model.json)
    device: str = "cpu"
    eval_every: int = 50          # this project's choice
    checkpoint_every: int = 500   # this project's choice
    # fraction of the steps that are albedo-swap pair steps (paper §6 trains both; the split is ours)
    pair_fraction: float = 0.5
    heldout_size: int = 512       # this project's choice: a fixed, seeded held-out set
    # network (reconstruction.network.architecture.NetworkConfig; paper §6 values)
    patterns_per_view: int = 32   # released: 32 signed patterns = 64 frames
    dropout: float = 0.3          # paper §6: 30%
    measurement_noise: float = 0.05  # paper §6: 5% multiplicative noise
    architecture: str = "paper"   # "paper" (released) or "compact" (shippable; reconstruction.network.architecture)
    peak_term: bool = False       # the decoder's lobe over the LEDs' directions (NetworkConfig.peak_term)
    # training data distributions (reconstruction.network.data.SamplingConfig defaults, sources given there)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    # a design's layout and pattern family (twin.design): lumitexel indices the patterns leave off, and a
    # pattern file of fixed (+, -) frames over all rig LEDs that the network uses as they are ("" = learn them)
    leds_off: tuple[int, ...] = ()
    patterns_file: str = ""

    def __post_init__(self):
        for name in ("steps", "batch", "eval_every", "checkpoint_every", "heldout_size", "patterns_per_view"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < (0 if name == "steps" else 1):
                raise ValueError(f"TrainConfig.{name} must be a {'non-negative' if name == 'steps' else 'positive'}"
                                 f" integer, got {v!r}")
        if not (isinstance(self.lr, (int, float)) and math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"TrainConfig.lr must be a positive number, got {self.lr!r}")
        if not 0.0 <= float(self.pair_fraction) <= 1.0:
            raise ValueError(f"TrainConfig.pair_fraction must lie in [0, 1], got {self.pair_fraction!r}")
        if isinstance(self.sampling, dict):
            object.__setattr__(self, "sampling", SamplingConfig(**self.sampling))

    def network_config(self, num_leds: int) -> NetworkConfig:
        return NetworkConfig(num_leds=int(num_leds), patterns_per_view=self.patterns_per_view,
                             dropout=self.dropout, measurement_noise=self.measurement_noise,
                             architecture=self.architecture, leds_off=self.leds_off,
                             fixed_patterns=bool(self.patterns_file), peak_term=bool(self.peak_term))

    def to_json(self) -> dict:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_json(cls, d: dict) -> "TrainConfig":
        d = dict(d)
        s = dict(d.pop("sampling", {}))
        for k, v in s.items():
            if isinstance(v, list):
                s[k] = tuple(v)
        d["leds_off"] = tuple(d.get("leds_off", ()))
        return cls(**d, sampling=SamplingConfig(**s))


def _fixed_weights(path, rig, count: int) -> np.ndarray:
    """(K, L_upper) signed grey weights of a pattern file of K (+, -) frame pairs over all rig LEDs."""
    from twin.capture.pattern_sets import signed_weights
    from twin.capture.patterns import PatternError, load_patterns

    try:
        p = load_patterns(path)
        p.check_rig(rig)
    except (PatternError, OSError) as e:
        raise TrainError(f"TrainConfig.patterns_file: {e}") from None
    if p.num_patterns != 2 * count:
        raise TrainError(f"TrainConfig.patterns_file: {path} has {p.num_patterns} frames, {count} patterns need "
                         f"{2 * count}")
    return signed_weights(p)[:, ~np.asarray(rig.is_bottom)]


def is_pair_step(i: int, fraction: float) -> bool:
    """Step i is an albedo-swap step when floor((i + 1) f) > floor(i f): evenly spaced, no RNG."""
    return math.floor((i + 1) * fraction) > math.floor(i * fraction)


# ------------------------------------------------------------------------------------------ checkpoints


def _rng_state(device: torch.device) -> dict:
    out = {"torch": torch.get_rng_state().tolist()}
    if device.type == "cuda":
        out["cuda"] = torch.cuda.get_rng_state(device).tolist()
    return out


def _set_rng_state(state: dict, device: torch.device) -> None:
    torch.set_rng_state(torch.tensor(state["torch"], dtype=torch.uint8))
    if device.type == "cuda" and "cuda" in state:
        torch.cuda.set_rng_state(torch.tensor(state["cuda"], dtype=torch.uint8), device)


def _save_checkpoint(run_dir: Path, model, opt, step: int, config: TrainConfig, rig_digest: str,
                     ctx: Dist, wall_s: float) -> None:
    """Every rank calls it (each rank's RNG state is kept); rank 0 writes."""
    from safetensors.torch import save_file

    rng = gather_objects(_rng_state(ctx.device), ctx)
    if not ctx.is_main:
        barrier(ctx)
        return

    tensors = {f"model.{k}": v.detach().cpu().contiguous().clone() for k, v in model.state_dict().items()}
    for pid, st in opt.state_dict()["state"].items():
        for key, v in st.items():
            t = v if torch.is_tensor(v) else torch.tensor(v)
            tensors[f"optim.{pid}.{key}"] = t.detach().cpu().contiguous().clone()
    before = _checkpoint_meta(run_dir)
    save = int(before.get("save", 0)) + 1 if before else 1  # new names every save: the old files stay valid
    shards, split = _shards(tensors, CHECKPOINT_SHARD_BYTES)
    names = [f"{_SHARD_PREFIX}{step:09d}-{save:04d}-{k:03d}.safetensors" for k in range(len(shards))]
    try:
        for name, shard in zip(names, shards):
            with atomic_path(run_dir / name) as tmp:
                save_file(shard, str(tmp), metadata={"step": str(step)})
    except BaseException:  # a failed save (a full disk) leaves none of its shards; the previous checkpoint stands
        for name in names:
            (run_dir / name).unlink(missing_ok=True)
        raise
    meta = {"format": "hemicube-train-checkpoint", "version": 2, "step": int(step), "save": save,
            "tensors": names, "sha256": [file_sha256(run_dir / n) for n in names], "split": split,
            "config": config.to_json(), "rig_digest": rig_digest, "rng": rng[0], "world_size": ctx.world,
            "wall_s": float(wall_s)}
    if ctx.active:
        meta["rng_ranks"] = rng
    write_bytes_atomic(run_dir / CHECKPOINT_JSON, json.dumps(meta).encode())
    # the files no checkpoint names now: the previous save's, and any a save killed before its JSON left
    for old in [*run_dir.glob(f"{_SHARD_PREFIX}*.safetensors"), run_dir / _LEGACY_TENSORS]:
        if old.name not in names:
            old.unlink(missing_ok=True)
    barrier(ctx)


def _shards(tensors: dict, limit: int) -> tuple[list[dict], dict]:
    """(shards, split): the tensors in order, in dicts of at most `limit` bytes each; a tensor of more than `limit`
    bytes is cut along its flattened elements into pieces "<name>@k", and split[name] is its shape."""
    shards, current, size, split = [], {}, 0, {}
    for name, t in tensors.items():
        if t.nbytes > limit:
            split[name] = list(t.shape)
            per = max(1, limit // t.element_size())
            parts = [(f"{name}@{k}", p.clone()) for k, p in enumerate(t.reshape(-1).split(per))]
        else:
            parts = [(name, t)]
        for key, p in parts:
            if current and size + p.nbytes > limit:
                shards.append(current)
                current, size = {}, 0
            current[key] = p
            size += p.nbytes
    return shards + ([current] if current else []), split


def _tensor_files(meta: dict) -> list[str]:
    """The tensor files a checkpoint.json names (version 1 named one file, _LEGACY_TENSORS, as a string)."""
    t = meta.get("tensors", [])
    return [t] if isinstance(t, str) else list(t)


def _checkpoint_meta(run_dir: Path) -> dict | None:
    """checkpoint.json's dict, or None when there is none."""
    jpath = run_dir / CHECKPOINT_JSON
    if not jpath.is_file():
        return None
    try:
        meta = json.loads(jpath.read_text())
    except (OSError, ValueError) as e:
        raise TrainError(f"{jpath}: not a readable checkpoint ({e})") from None
    if not isinstance(meta, dict):
        raise TrainError(f"{jpath}: not a readable checkpoint (not a JSON object)")
    return meta


def _resume_rng(meta: dict, ctx: Dist, seed: int) -> None:
    """Each rank's RNG as it was at the checkpoint; a run resumed on another number of processes reseeds
    every rank instead (dropout and noise draws then differ from an uninterrupted run; the data do not)."""
    saved = meta.get("rng_ranks", [meta["rng"]])
    if len(saved) == ctx.world:
        _set_rng_state(saved[ctx.rank], ctx.device)
        return
    if ctx.is_main:
        print(f"train: the checkpoint was written by {len(saved)} process(es), this run has {ctx.world}: the "
              "model, optimiser and data stream resume exactly; dropout and measurement-noise draws are reseeded",
              file=sys.stderr)
    torch.manual_seed(stream_seed(seed, f"resume-rank-{ctx.rank}", int(meta["step"])))


def load_checkpoint(run_dir) -> tuple[dict, dict] | None:
    """(checkpoint.json's dict, tensors on the CPU) of a run folder, or None when it has no checkpoint. Every
    shard file's sha256 is checked against the JSON's."""
    from safetensors.torch import load_file

    run_dir = Path(run_dir)
    meta = _checkpoint_meta(run_dir)
    if meta is None:
        return None
    names = _tensor_files(meta)
    shas = meta.get("sha256")
    shas = [shas] if isinstance(shas, str) else list(shas or [])
    tensors = {}
    for k, name in enumerate(names):
        path = run_dir / name
        if not path.is_file() or k >= len(shas) or file_sha256(path) != shas[k]:
            raise TrainError(f"{run_dir / CHECKPOINT_JSON} names {name}, which is missing or has another sha256 "
                             "(changed after the checkpoint was written); restore the file or start a new run folder")
        tensors.update(load_file(str(path)))
    if not names:
        raise TrainError(f"{run_dir / CHECKPOINT_JSON} names no tensor file")
    for name, shape in meta.get("split", {}).items():
        keys = sorted((k for k in tensors if k.rsplit("@", 1)[0] == name and "@" in k),
                      key=lambda k: int(k.rsplit("@", 1)[1]))
        try:
            tensors[name] = torch.cat([tensors.pop(k) for k in keys]).reshape(shape)
        except (RuntimeError, TypeError, ValueError):
            raise TrainError(f"{run_dir / CHECKPOINT_JSON}: the pieces of {name} do not make its shape {shape}; "
                             "restore the checkpoint or start a new run folder") from None
    return meta, tensors


def load_run_model(run_dir, device="cpu") -> AcquisitionNet:
    """The network of a `hemicube train` run folder (its latest checkpoint), in eval mode."""
    import twin

    ckpt = load_checkpoint(run_dir)
    if ckpt is None:
        raise TrainError(f"{run_dir}: not a training run folder (no {CHECKPOINT_JSON})")
    meta, tensors = ckpt
    config = TrainConfig.from_json(meta["config"])
    rig = twin.load_rig(config.rig)
    if rig.digest() != meta.get("rig_digest"):
        raise TrainError(f"{run_dir}: trained on a rig (digest {meta.get('rig_digest')}) other than {config.rig!r}")
    model = AcquisitionNet(config.network_config(int((~np.asarray(rig.is_bottom)).sum())))
    model.load_state_dict({k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")})
    return model.to(device).eval()


def _check_resumable(meta: dict, config: TrainConfig, rig_digest: str, run_dir: Path) -> None:
    # a field the checkpoint lacks was added after it was written: it ran with that field's default
    old = {k: v for k, v in {**TrainConfig().to_json(), **meta["config"]}.items() if k not in RESUMABLE_FIELDS}
    new = {k: v for k, v in config.to_json().items() if k not in RESUMABLE_FIELDS}
    if old != new:
        diff = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
        detail = ", ".join(f"{k}: {old.get(k)!r} (checkpoint) != {new.get(k)!r} (now)" for k in diff)
        raise TrainError(f"{run_dir} holds a checkpoint of a run with a different config ({detail}); resume "
                         "with the same settings (only steps, eval_every, checkpoint_every and device may "
                         "change) or use another run folder")
    if meta.get("rig_digest") != rig_digest:
        raise TrainError(f"{run_dir} holds a checkpoint trained on a different rig (digest "
                         f"{meta.get('rig_digest')} != {rig_digest}); use another run folder")


def _restore(model, opt, tensors: dict) -> None:
    model.load_state_dict({k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")})
    state: dict = {}
    for k, v in tensors.items():
        if k.startswith("optim."):
            _, pid, key = k.split(".", 2)
            state.setdefault(int(pid), {})[key] = v
    opt.load_state_dict({"state": state, "param_groups": opt.state_dict()["param_groups"]})


# ------------------------------------------------------------------------------------------ outputs


def export_patterns(model: AcquisitionNet, rig, note: str = ""):
    """The learned patterns of view 0 as a twin.capture.patterns.PatternSet over ALL rig LEDs (bottom LEDs 0,
    3 equal channels), frames in the capture plan's order."""
    from twin.capture.patterns import PatternSet

    lv = model.patterns.export_levels(0)  # (2K, L_upper) uint8
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    if lv.shape[1] != upper.size:
        raise ValueError(f"the model has {lv.shape[1]} LEDs per pattern, rig {rig.name!r} has {upper.size} upper LEDs")
    full = np.zeros((lv.shape[0], rig.num_leds, 3), dtype=np.uint8)
    full[:, upper, :] = lv[:, :, None]
    return PatternSet(full, tuple(model.patterns.export_names()), rig.name, note)


def read_metrics(path: Path, max_step: int | None = None) -> list[dict]:
    """The rows of a run's metrics.jsonl (one an evaluation), up to `max_step`; a line cut short by a kill is skipped."""
    rows = []
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                r = json.loads(line)
            except ValueError:
                continue  # a line cut short by a kill
            if max_step is None or r["step"] <= max_step:
                rows.append(r)
    return rows


def _plot_loss(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    tr = [(r["step"], r["train_loss"]) for r in rows if r.get("train_loss") is not None]
    he = [(r["step"], r["heldout_loss"]) for r in rows]
    if tr:
        ax.plot(*zip(*tr), label="train (Eq. 3 per lumitexel)")
    if he:
        ax.plot(*zip(*he), marker="o", ms=3, label="held-out (Eq. 3)")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


# ------------------------------------------------------------------------------------------ training


def heldout_losses(model, held) -> torch.Tensor:
    """Eq. 3 of each held-out texel, in eval mode (no dropout, BatchNorm's running statistics); the model is
    left in eval mode."""
    model.eval()
    with torch.no_grad():
        return lumitexel_loss(model(held["views"])["log_lumitexel"], held["target"], reduction="none")


def blind_loss(target: torch.Tensor) -> float:
    """Eq. 3 of the best measurement-blind predictor of the lumitexels `target` (n, L): the per-LED mean of
    log(1 + m) over them, i.e. their summed per-LED variance of log(1 + m). A network that ignores its
    measurements (a collapsed decoder) scores this; a useful one scores well below it."""
    logs = torch.log1p(target.double())
    return float(((logs - logs.mean(dim=0)) ** 2).sum(dim=1).mean())


def _evaluate(model, held) -> float:
    loss = float(heldout_losses(model, held).mean())
    model.train()
    return loss


def train(config: TrainConfig, run_dir, progress: bool = True, time_limit: float | None = None) -> dict:
    """Train (or resume) the acquisition network in `run_dir`; return the summary written to metrics.json.
    time_limit: seconds from this call's start after which the run checkpoints and stops (see "Chunks")."""
    t_call = time.perf_counter()  # the limit counts setup too (rig, held-out set, a 2 GB checkpoint load)
    import twin
    from twin.progress import progress_bar
    from twin.capture.patterns import save_patterns

    if not isinstance(config, TrainConfig):
        raise ValueError(f"config must be a TrainConfig, got {type(config).__name__}")
    if time_limit is not None and not (isinstance(time_limit, (int, float)) and time_limit >= 0):
        raise ValueError(f"time_limit must be a number of seconds >= 0, got {time_limit!r}")
    run_dir = Path(run_dir)
    source, _, maps = config.sampling.materials.partition(":")
    claim_output(run_dir, RUN_FOLDER, [("the rig folder", config.rig), ("the pattern file", config.patterns_file),
                                       ("the training maps", maps if source == "maps" else None)])
    ctx = join(config.device)  # torchrun's process group, if any (reconstruction.network.distributed)
    device = ctx.device
    if config.batch % ctx.world:
        raise TrainError(f"the global batch ({config.batch}) must be a multiple of the {ctx.world} processes")
    rig = twin.load_rig(config.rig)
    digest = rig.digest()
    ckpt = load_checkpoint(run_dir)
    if ckpt is not None:
        _check_resumable(ckpt[0], config, digest, run_dir)
    if ctx.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)

    threads = torch.get_num_threads()
    if device.type == "cpu":
        torch.set_num_threads(1)  # tiny models: one thread is far faster when cores are shared
    try:
        num_upper = int((~np.asarray(rig.is_bottom)).sum())
        net_cfg = config.network_config(num_upper)
        stream = LumitexelStream(rig, config.sampling, config.batch, config.seed, device, shard=(ctx.rank, ctx.world))
        # the held-out set is evaluated by rank 0 alone (eval mode: no cross-rank statistics)
        held = heldout_set(rig, config.sampling, config.heldout_size, config.seed, device) if ctx.is_main else None
        torch.manual_seed(config.seed)
        model = AcquisitionNet(net_cfg)
        if net_cfg.peak_term:
            model.decoder.set_led_directions(led_directions(rig))
        model = model.to(device)
        if config.patterns_file:
            model.patterns.set_weights(_fixed_weights(config.patterns_file, rig, config.patterns_per_view))
        model.train()
        if ctx.active:
            globalise_batchnorm(model)
            torch.manual_seed(stream_seed(config.seed, f"rank-{ctx.rank}", 0))  # own dropout and noise draws
        opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=config.lr,
                               betas=(config.beta1, config.beta2))

        mpath = run_dir / "metrics.jsonl"
        start, wall_before = 0, 0.0
        if ckpt is not None:
            meta, tensors = ckpt
            _restore(model, opt, {k: v.to(device) for k, v in tensors.items()})
            _resume_rng(meta, ctx, config.seed)
            start, wall_before = int(meta["step"]), float(meta.get("wall_s", 0.0))
            if ctx.is_main:  # drop evaluations written after the checkpoint (a killed run): they are redone
                kept = read_metrics(mpath, max_step=start)
                write_bytes_atomic(mpath, "".join(json.dumps(r) + "\n" for r in kept).encode())
        elif ctx.is_main and mpath.exists():
            mpath.unlink()
        if ctx.active:  # gradients averaged over the ranks (reconstruction.network.distributed)
            from torch.nn.parallel import DistributedDataParallel

            net = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
        else:
            net = model
        barrier(ctx)  # rank 0 has tidied the folder before anyone goes on

        t0 = time.perf_counter()
        last_eval_t, last_samples = t0, 0
        samples, window_plain, window_swap = 0, [], []
        heldout, stopped = None, False
        with open(mpath, "a") if ctx.is_main else contextlib.nullcontext() as mf:
            def log(step: int):
                nonlocal last_eval_t, last_samples, window_plain, window_swap, heldout
                # the window's losses stay on the device until here (no host sync per step); every rank takes
                # part in the sum over ranks: the global batch's mean loss, step by step
                plain, swap = (float((all_sum(torch.stack(w).double(), ctx) / ctx.world).mean()) if w else None
                               for w in (window_plain, window_swap))
                window_plain, window_swap = [], []
                if not ctx.is_main:
                    return None
                now = time.perf_counter()
                heldout = _evaluate(model, held)
                row = {"step": step, "train_loss": plain, "train_swap_loss": swap,
                       "heldout_loss": heldout, "wall_s": wall_before + (now - t0),
                       "lumitexels_per_s": ((samples - last_samples) / (now - last_eval_t)
                                            if samples > last_samples else None)}
                mf.write(json.dumps(row) + "\n")
                mf.flush()
                os.fsync(mf.fileno())
                last_eval_t, last_samples = time.perf_counter(), samples
                return row

            if start == 0:
                log(0)
            bar = progress_bar(range(start, config.steps), initial=start, total=config.steps,
                               enabled=progress and ctx.is_main, desc="train", unit="step", file=sys.stderr)
            for i in bar:
                if is_pair_step(i, config.pair_fraction):
                    b = stream.pair_batch(i)
                    loss = albedo_swap_loss(net(b["views_a"], pair_with=b["views_b"])["swap_log_lumitexel"],
                                            b["targets"])
                    n = 2 * config.batch
                else:
                    b = stream.batch(i)
                    loss = lumitexel_loss(net(b["views"])["log_lumitexel"], b["views"][:, 0])
                    n = config.batch
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                lv = loss.detach()
                if n == config.batch:
                    window_plain.append(lv)
                else:
                    window_swap.append(lv)
                    window_plain.append(lv / 4.0)
                samples += n  # the global batch: n counts every rank's samples
                step = i + 1
                if step % config.eval_every == 0 or step == config.steps:
                    row = log(step)
                    if row is not None:
                        bar.set_postfix(heldout=f"{row['heldout_loss']:.3g}")
                if step % config.checkpoint_every == 0 and step != config.steps:
                    _save_checkpoint(run_dir, model, opt, step, config, digest, ctx,
                                     wall_before + time.perf_counter() - t0)
                # chunk over: every rank stops after the same step (any rank's clock decides)
                if time_limit is not None and step != config.steps and \
                        any_rank(time.perf_counter() - t_call >= time_limit, ctx):
                    # evaluate here unless just done (held-out eval uses no RNG, so the resumed run still
                    # equals an uninterrupted one), then checkpoint below at `step`
                    stopped = True
                    if step % config.eval_every != 0:
                        log(step)
                    break
            bar.close()
            end = step if stopped else max(start, config.steps)
            if heldout is None and ctx.is_main:  # nothing run (resumed at or past the end): evaluate what is there
                heldout = _evaluate(model, held)
        loop_s = time.perf_counter() - t0
        ran = end - start
        if ran or ckpt is None:  # a run resumed at its end already has this checkpoint: do not write it again
            _save_checkpoint(run_dir, model, opt, end, config, digest, ctx, wall_before + loop_s)
        if not ctx.is_main:
            return {}

        note = (f"learned by reconstruction.network.train: rig {rig.name}, step {end}, seed {config.seed}, "
                f"held-out loss (Eq. 3) {heldout:.6g}")
        save_patterns(export_patterns(model, rig, note), run_dir / "patterns.npz")
        rows = read_metrics(mpath)
        _plot_loss(rows, run_dir / "loss.png")
        summary = {"final_heldout_loss": heldout, "steps": end, "steps_this_invocation": ran,
                   "target_steps": config.steps, "stopped_on_time_limit": stopped, "time_limit_s": time_limit,
                   "resumed_from": start if ckpt is not None else None,
                   "wall_s": wall_before + loop_s, "wall_s_this_invocation": loop_s,
                   "iterations_per_s": ran / loop_s if ran and loop_s > 0 else None,
                   "lumitexels_per_s": samples / loop_s if samples and loop_s > 0 else None,
                   "num_parameters": int(sum(p.numel() for p in model.parameters())),
                   "num_upper_leds": num_upper, "rig": rig.name, "rig_digest": digest,
                   "device": str(device), "world_size": ctx.world, "backend": ctx.backend,
                   "torch_threads": torch.get_num_threads(),
                   "config": config.to_json(), "command_line": list(sys.argv)}
        write_bytes_atomic(run_dir / "metrics.json", (json.dumps(summary, indent=2) + "\n").encode())
        return summary
    finally:
        torch.set_num_threads(threads)

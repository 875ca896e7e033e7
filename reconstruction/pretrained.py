"""Pretrained acquisition networks shipped inside the package, so that `hemicube validate` and the
capture plan need no training.

    reconstruction/pretrained/<rig>/model.safetensors   the network's weights (safetensors)
    reconstruction/pretrained/<rig>/model.json          how it was made: the `hemicube train` command,
                                                        its TrainConfig, seed, steps, rig digest, and
                                                        the held-out Eq. 3 loss it reached

Only the `mini` rig's model ships (260 k parameters, ~1 MB). Its learned patterns are the capture plan's
default for that rig: `write_default_patterns` stores them as data the rig carries
(twin.capture.plan.DEFAULT_PATTERNS), since `twin` sits below `reconstruction` and never imports it; after
shipping a retrained network, run
    python -c "from reconstruction.pretrained import write_default_patterns; write_default_patterns('mini')"
(tests/test_pretrained.py fails while the two disagree).
"""
from __future__ import annotations

import json
from pathlib import Path

import torch

from twin.atomic import write_bytes_atomic

from .network import AcquisitionNet
from .train import TrainConfig, _evaluate, export_patterns

PRETRAINED_DIR = Path(__file__).resolve().parent / "pretrained"


def pretrained_info(rig_name: str) -> dict | None:
    path = PRETRAINED_DIR / rig_name / "model.json"
    return json.loads(path.read_text()) if path.is_file() else None


def load_pretrained(rig_name: str = "mini", device: str = "cpu") -> tuple[AcquisitionNet, dict]:
    """The shipped network for a built-in rig, in eval mode, and its model.json."""
    from safetensors.torch import load_file

    info = pretrained_info(rig_name)
    if info is None:
        raise FileNotFoundError(f"no pretrained network ships for rig {rig_name!r} "
                                f"(available: {sorted(p.name for p in PRETRAINED_DIR.iterdir() if p.is_dir())})")
    config = TrainConfig.from_json(info["config"])
    model = AcquisitionNet(config.network_config(info["num_upper_leds"]))
    model.load_state_dict(load_file(str(PRETRAINED_DIR / rig_name / "model.safetensors")))
    return model.to(device).eval(), info


def pretrained_patterns(rig):
    """The shipped network's learned patterns for `rig` (a twin.capture.patterns.PatternSet), or None when no
    network ships for it or it was trained on a different rig (twin.rig.builtin.serves_for: a calibration of the cameras'
    light recording keeps it)."""
    from twin.rig.builtin import serves_for

    info = pretrained_info(rig.name)
    if info is None or not serves_for(rig, info["rig_digest"]):
        return None
    model, info = load_pretrained(rig.name)
    return export_patterns(model, rig, note=f"learned patterns of the shipped {rig.name} network "
                                            f"({info['command']})")


def write_default_patterns(rig_name: str) -> None:
    """Store the shipped network's learned patterns as the built-in rig's default capture patterns."""
    import tomllib

    import tomli_w

    import twin
    from twin.capture.patterns import save_patterns
    from twin.capture.plan import DEFAULT_PATTERNS

    rig = twin.load_rig(rig_name)
    patterns = pretrained_patterns(rig)
    if patterns is None:
        raise ValueError(f"no network ships for rig {rig_name!r} (or it was trained on another version of it)")
    index_path = DEFAULT_PATTERNS / "index.toml"
    index = tomllib.loads(index_path.read_text()) if index_path.is_file() else {}
    index[rig_name] = {"file": f"{rig_name}.npz", "rig_digest": rig.digest(),
                       "source": f"reconstruction/pretrained/{rig_name}: the shipped network's learned patterns"}
    save_patterns(patterns, DEFAULT_PATTERNS / f"{rig_name}.npz")
    write_bytes_atomic(index_path, tomli_w.dumps(index).encode())


def heldout_loss(rig_name: str = "mini", device: str = "cpu") -> float:
    """Re-evaluate the shipped network on its run's seeded held-out set (Eq. 3)."""
    import twin

    from .data import heldout_set

    model, info = load_pretrained(rig_name, device)
    config = TrainConfig.from_json(info["config"])
    rig = twin.load_rig(rig_name)
    held = heldout_set(rig, config.sampling, config.heldout_size, config.seed, torch.device(device))
    return _evaluate(model, held)

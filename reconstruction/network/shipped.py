"""Pretrained acquisition networks shipped inside the package, so that `hemicube validate` and the
capture plan need no training.

    reconstruction/pretrained/<rig>/model.safetensors   the network's weights (safetensors)
    reconstruction/pretrained/<rig>/model.json          how it was made: the `hemicube train` command,
                                                        its TrainConfig, seed, steps, rig digest, the
                                                        held-out Eq. 3 loss it reached, and the weights
                                                        file's sha256 (checked on every load)

Two ship: `mini` (260 k parameters, float32, ~1 MB) and `paper` (the compact architecture,
reconstruction.network.architecture, 6.5 M parameters: its weight matrices in float16, the rest float32, 13 MB; the
released architecture's 698 MB cannot ship). `ship_network` makes both files from a `hemicube train` run
(`hemicube network ship RUN`): it rounds the weights as they will ship, then scores the rounded network, so
model.json describes exactly what loads. A file must stay within SHIP_LIMIT (16 MiB), the largest the lent GPU
machines return and a size a repository carries. Each network's learned patterns are the capture plan's
default for its rig: `write_default_patterns` stores them as data the rig carries
(twin.capture.plan.DEFAULT_PATTERNS), since `twin` sits below `reconstruction` and never imports it; after
shipping a retrained network, run
    python -c "from reconstruction.network.shipped import write_default_patterns; write_default_patterns('mini')"
(tests/test_pretrained.py fails while the two disagree).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import torch

from twin.atomic import write_bytes_atomic
from twin.outputs import Kind, claim_output

from reconstruction.network.data import heldout_set
from reconstruction.network.architecture import AcquisitionNet, log_to_lumitexel, lumitexel_loss
from reconstruction.network.train import TrainConfig, _evaluate, blind_loss, export_patterns, heldout_losses, load_run_model

PRETRAINED_DIR = Path(__file__).resolve().parents[1] / "pretrained"
# `network ship -o`'s folder, whose two files a ship replaces (twin.outputs)
SHIPPED_FOLDER = Kind("a shipped network folder", ("model.json",))
SHIP_LIMIT = 16 * 2 ** 20
NARROW_ALPHA = 0.02   # the specular peak is scored on lobes with alpha_x, alpha_y <= this
FIRST_TEXELS = 8      # per-texel held-out losses kept in model.json, re-evaluated on the CPU in CI


def pretrained_info(rig_name: str) -> dict | None:
    path = PRETRAINED_DIR / rig_name / "model.json"
    return json.loads(path.read_text()) if path.is_file() else None


def load_pretrained(rig_name: str = "mini", device: str = "cpu") -> tuple[AcquisitionNet, dict]:
    """The shipped network for a built-in rig ("mini", "paper"), in eval mode on `device` ("cpu", "cuda"), and its
    model.json as a dict (how it was made: the TrainConfig, steps, the rig's digest, its held-out Eq. 3 loss and
    scores). The network (reconstruction.network.architecture.AcquisitionNet, a torch module) maps lumitexels
    (B, views, L) of the rig's L upper LEDs to measurements (B, views, K) under its K learned patterns and decodes
    latents to log lumitexels (B, L). A rig with none shipped is a FileNotFoundError."""
    if pretrained_info(rig_name) is None:
        raise FileNotFoundError(f"no pretrained network ships for rig {rig_name!r} "
                                f"(available: {sorted(p.name for p in PRETRAINED_DIR.iterdir() if p.is_dir())})")
    return load_shipped(PRETRAINED_DIR / rig_name, device)


def load_shipped(folder, device: str = "cpu") -> tuple[AcquisitionNet, dict]:
    """The network of a folder `ship_network` wrote, in eval mode, and its model.json. The weights must be the
    file model.json describes (its weights_sha256): the two files are written one after the other, so a ship
    killed between them, or a weights file swapped or damaged since, would otherwise load weights that the
    recorded scores and patterns do not belong to."""
    from safetensors.torch import load

    folder = Path(folder)
    info = json.loads((folder / "model.json").read_text())
    blob = (folder / "model.safetensors").read_bytes()
    digest = hashlib.sha256(blob).hexdigest()
    if digest != info.get("weights_sha256"):
        raise ValueError(f"{folder / 'model.safetensors'}: its sha256 {digest[:12]}... is not the "
                         f"{str(info.get('weights_sha256'))[:12]}... that model.json records (a ship that did not "
                         "finish, or a changed file); ship the network again (`hemicube network ship RUN`)")
    config = TrainConfig.from_json(info["config"])
    model = AcquisitionNet(config.network_config(info["num_upper_leds"]))
    model.load_state_dict(load(blob))
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


def score_network(model: AcquisitionNet, rig, config: TrainConfig, device="cpu") -> dict:
    """Held-out figures of a network (eval mode) on its run's seeded held-out sets:
    heldout_loss   Eq. 3, the mean over the held-out set (as training reports it);
    heldout_first  the first FIRST_TEXELS texels' own Eq. 3 values (re-evaluated on the CPU by the tests);
    blind_loss     the best measurement-blind predictor's Eq. 3 (the per-LED mean log(1 + m)): a network that
                   ignores its input scores this;
    narrow         a second held-out set drawn alike but with alpha_x, alpha_y <= NARROW_ALPHA, scored on each
                   texel's specular peak (the LEDs at or above half the texel's largest value):
                   peak_log_rms, the median over texels of the RMS error of log(1 + m) there, and
                   peak_energy, the median |sum m_hat / sum m - 1| there (the peak's light, which fine-tuning
                   and the fit lean on), with the whole lumitexels' Eq. 3 for scale."""
    held = heldout_set(rig, config.sampling, config.heldout_size, config.seed, device)
    per = heldout_losses(model, held)
    blind = blind_loss(held["target"])
    lo = config.sampling.alpha_range[0]
    narrow = heldout_set(rig, dataclasses.replace(config.sampling, alpha_range=(lo, max(lo, NARROW_ALPHA))),
                         config.heldout_size, config.seed, device)
    m = narrow["target"].double()
    with torch.no_grad():  # heldout_losses left the model in eval mode
        m_hat = log_to_lumitexel(model(narrow["views"])["log_lumitexel"]).double()
    peak = m >= 0.5 * m.max(dim=1, keepdim=True).values
    d2 = (torch.log1p(m_hat) - torch.log1p(m)) ** 2
    rms = torch.sqrt((d2 * peak).sum(dim=1) / peak.sum(dim=1))
    energy = ((m_hat * peak).sum(dim=1) / (m * peak).sum(dim=1).clamp_min(1e-30) - 1).abs()
    return {"heldout_loss": float(per.mean()), "heldout_first": [float(v) for v in per[:FIRST_TEXELS]],
            "blind_loss": blind, "heldout_size": int(per.numel()),
            "narrow": {"alpha_max": NARROW_ALPHA, "texels": int(m.shape[0]),
                       "loss": float(lumitexel_loss(torch.log1p(m_hat), m)),
                       "peak_leds_median": float(peak.sum(dim=1).double().median()),
                       "peak_log_rms": float(rms.median()), "peak_energy": float(energy.median())}}


def _as_shipped(state: dict) -> dict:
    """The tensors as they ship: weight matrices and the patterns (ndim >= 2) in float16, biases, the BatchNorm
    statistics (whose variances may exceed float16's range) and the peak term's LED directions in float32 (a unit
    vector rounded to float16 is off by up to 5e-4, which a narrow lobe's kappa of 10^4 turns into e^5)."""
    return {k: (v.detach().half() if v.ndim >= 2 and v.is_floating_point() and not k.endswith("led_directions")
                else v.detach()).cpu().contiguous()
            for k, v in state.items()}


def ship_network(run_dir, dest=None, device="cpu", commit: str = "") -> dict:
    """Make reconstruction/pretrained/<rig>/ (or `dest`) from a `hemicube train` run: model.safetensors with the
    weights as they ship (`_as_shipped`) and model.json with how the run was made and `score_network`'s figures
    of the shipped (rounded) network. Refuses a file above SHIP_LIMIT. Returns model.json's dict."""
    from safetensors.torch import save

    import twin

    run_dir = Path(run_dir)
    tensors = _as_shipped(load_run_model(run_dir).state_dict())  # first: a folder that is no run says so
    if not (run_dir / "metrics.json").is_file():
        raise ValueError(f"{run_dir}: no metrics.json (a run killed before its call ended); run the same "
                         "`hemicube train` command again to finish it")
    summary = json.loads((run_dir / "metrics.json").read_text())
    config = TrainConfig.from_json(summary["config"])
    rig = twin.load_rig(config.rig)
    out = Path(dest) if dest else PRETRAINED_DIR / rig.name
    claim_output(out, SHIPPED_FOLDER, [("the run being shipped", run_dir)])  # before the scoring
    blob = save(tensors)
    if len(blob) > SHIP_LIMIT:
        raise ValueError(f"{run_dir}: its network is {len(blob) / 2 ** 20:.1f} MiB as it would ship, above the "
                         f"{SHIP_LIMIT / 2 ** 20:.0f} MiB a shipped file may have; train --architecture compact")
    model = AcquisitionNet(config.network_config(summary["num_upper_leds"]))
    model.load_state_dict(tensors)
    scores = score_network(model.to(device), rig, config, torch.device(device))
    command = summary["command_line"]
    info = {"format": "hemicube-pretrained", "version": 1,
            "command": " ".join(["hemicube", *command[1:]]) if command else "",
            "made_at_commit": commit, "seed": config.seed, "steps": summary["steps"], "rig": rig.name,
            "rig_digest": summary["rig_digest"], "num_upper_leds": summary["num_upper_leds"],
            "num_parameters": summary["num_parameters"], "architecture": config.architecture,
            "storage": "float16 weight matrices and patterns, float32 biases and BatchNorm statistics",
            "heldout_loss": scores["heldout_loss"], "weights_sha256": hashlib.sha256(blob).hexdigest(),
            "heldout": {"size": config.heldout_size, "seed": config.seed,
                        "loss": "Eq. 3, mean over texels of sum over LEDs of (log(1+m_hat) - log(1+m))^2"},
            "scores": scores, "scored_on": str(torch.cuda.get_device_name() if device.startswith("cuda") else device),
            "train_wall_s": summary["wall_s"], "iterations_per_s": summary["iterations_per_s"],
            "lumitexels_per_s": summary["lumitexels_per_s"], "device": summary["device"],
            "config": summary["config"]}
    out.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(out / "model.safetensors", blob)
    write_bytes_atomic(out / "model.json", (json.dumps(info, indent=1) + "\n").encode())
    return info


def heldout_loss(rig_name: str = "mini", device: str = "cpu") -> float:
    """Re-evaluate the shipped network on its run's seeded held-out set (Eq. 3)."""
    import twin

    model, info = load_pretrained(rig_name, device)
    config = TrainConfig.from_json(info["config"])
    rig = twin.load_rig(rig_name)
    held = heldout_set(rig, config.sampling, config.heldout_size, config.seed, torch.device(device))
    return _evaluate(model, held)

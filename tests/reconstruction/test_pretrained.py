"""The pretrained networks that ship in the package (mini, and the compact paper-rig one)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import twin
from reconstruction.network.shipped import heldout_loss, load_pretrained, pretrained_info, pretrained_patterns
from twin.capture.plan import build_patterns


def test_shipped_mini_model_reaches_its_documented_heldout_loss():
    """Re-evaluated on its run's seeded held-out set, the shipped network gives the loss written beside it.
    Everything is seeded and runs on the CPU in float32: equal to float32 rounding (rtol 1e-5)."""
    info = pretrained_info("mini")
    assert info["command"].startswith("hemicube train --rig mini") and info["seed"] == 0 and info["steps"] > 0
    assert heldout_loss("mini") == pytest.approx(info["heldout_loss"], rel=1e-5)
    assert info["heldout_loss"] < 20  # untrained: ~1.6e4 (Eq. 3 summed over the 396 upper LEDs)


def test_shipped_mini_model_uses_its_latent():
    """The decoder must depend on the measurements: its held-out loss must be well below that of the best
    measurement-blind predictor, the per-LED mean of log(1 + m) over the held-out set (Eq. 3 = the summed
    per-LED variance). A network trained with the paper's 30% dropout on the mini rig's 64-wide layers
    collapsed to that predictor (ratio 1.00); a working one sits far below. Bound: half of it."""
    import torch

    from reconstruction.network.data import heldout_set
    from reconstruction.network.train import TrainConfig

    info = pretrained_info("mini")
    config = TrainConfig.from_json(info["config"])
    held = heldout_set(twin.load_rig("mini"), config.sampling, config.heldout_size, config.seed)
    logs = torch.log1p(held["target"].double())
    blind = float(((logs - logs.mean(dim=0)) ** 2).sum(dim=1).mean())
    assert info["heldout_loss"] < 0.5 * blind, (info["heldout_loss"], blind)


@pytest.mark.parametrize("rig_name", ["mini", "paper"])
def test_shipped_patterns_are_the_capture_default(rig_name):
    rig = twin.load_rig(rig_name)
    learned = pretrained_patterns(rig)
    assert learned.levels.shape == (64, rig.num_leds, 3) and learned.names[:2] == ("learned_00+", "learned_00-")
    assert not np.any((learned.levels[0::2] > 0) & (learned.levels[1::2] > 0))  # a signed pair never overlaps
    assert np.all(learned.levels[:, rig.is_bottom] == 0)
    plan = build_patterns(rig)
    np.testing.assert_array_equal(plan.levels[:64], learned.levels)


def test_shipped_paper_model_scores_on_the_cpu_as_recorded():
    """The compact paper-rig network ships within 16 MiB and, re-evaluated on the CPU on the first
    texels of its seeded held-out set, gives the per-texel Eq. 3 values recorded on the GPU (float32 on two
    devices: rtol 1e-3); it is far below the measurement-blind predictor."""
    import torch

    from reconstruction.network.data import heldout_set
    from reconstruction.network.architecture import lumitexel_loss
    from reconstruction.network.shipped import FIRST_TEXELS, PRETRAINED_DIR, SHIP_LIMIT
    from reconstruction.network.train import TrainConfig

    assert (PRETRAINED_DIR / "paper" / "model.safetensors").stat().st_size <= SHIP_LIMIT
    model, info = load_pretrained("paper")
    assert info["architecture"] == "compact" and info["num_upper_leds"] == 12288
    config = TrainConfig.from_json(info["config"])
    held = heldout_set(twin.load_rig("paper"), config.sampling, config.heldout_size, config.seed)
    with torch.no_grad():
        per = lumitexel_loss(model(held["views"][:FIRST_TEXELS])["log_lumitexel"], held["target"][:FIRST_TEXELS],
                             reduction="none")
    np.testing.assert_allclose(per.numpy(), info["scores"]["heldout_first"], rtol=1e-3, atol=1e-3)
    assert info["heldout_loss"] < 0.25 * info["scores"]["blind_loss"]


def test_no_model_for_other_rigs(tmp_path):
    with pytest.raises(FileNotFoundError, match="no pretrained network ships for rig 'nosuch'"):
        load_pretrained("nosuch")
    model, info = load_pretrained("mini")
    assert not model.training and info["num_upper_leds"] == 396
    for rig_name in ("mini", "paper"):  # the shipped pairs match (load_pretrained checks every load)
        assert pretrained_info(rig_name)["weights_sha256"]


def test_compact_architecture_fits_the_ship_limit_and_ships_as_scored(tmp_path):
    """The compact paper-rig network is within SHIP_LIMIT as float16 matrices; `hemicube network ship` of a tiny
    mini-rig compact run writes float16 matrices whose re-scoring gives model.json's loss; a folder that is no
    run gets a one-line error and no output folder."""
    import hemicube.cli
    from reconstruction.network.architecture import AcquisitionNet, NetworkConfig, decoder_widths
    from reconstruction.network.shipped import SHIP_LIMIT, score_network
    from reconstruction.network.train import TrainConfig, load_run_model

    assert decoder_widths(12288, 56, "compact") == [56, 128, 256, 256, 512, 1024, 256, 12288]
    assert sum(p.numel() for p in AcquisitionNet(NetworkConfig(12288, architecture="compact")).parameters()) \
        * 2 < SHIP_LIMIT
    run, dest = tmp_path / "run", tmp_path / "ship"
    assert hemicube.cli.main(["train", "--rig", "mini", "--architecture", "compact", "--steps", "4",
                              "--eval-every", "2", "--no-progress", "-o", str(run)]) == 0
    assert hemicube.cli.main(["network", "ship", str(run), "-o", str(dest)]) == 0
    from safetensors.torch import load_file

    tensors = load_file(str(dest / "model.safetensors"))
    floats = [t for t in tensors.values() if t.dtype.is_floating_point]  # (BatchNorm's step counts are integers)
    assert floats and all((t.dtype == torch.float16) == (t.ndim >= 2) for t in floats)
    info = json.loads((dest / "model.json").read_text())
    model = AcquisitionNet(TrainConfig.from_json(info["config"]).network_config(396))
    model.load_state_dict(tensors)
    again = score_network(model, twin.load_rig("mini"), TrainConfig.from_json(info["config"]))
    assert again["heldout_loss"] == pytest.approx(info["heldout_loss"], rel=1e-6)
    assert load_run_model(run).decoder.widths[-2] == 64  # the bottleneck, scaled and at least 64
    # model.json names its weights by sha256: a ship killed between its two files, or a weights file changed
    # since, gives a one-line error on load instead of weights the recorded scores do not describe
    from reconstruction.network.shipped import load_shipped

    loaded, _ = load_shipped(dest)
    assert all(torch.equal(loaded.state_dict()[k].float(), model.state_dict()[k].float()) for k in tensors)
    blob = bytearray((dest / "model.safetensors").read_bytes())
    blob[-1] ^= 1
    (dest / "model.safetensors").write_bytes(bytes(blob))
    with pytest.raises(ValueError, match=r"model\.safetensors: its sha256 .* is not the .* that model\.json records") as e:
        load_shipped(dest)
    assert "\n" not in str(e.value)
    assert hemicube.cli.main(["network", "ship", str(tmp_path / "none"), "-o", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()


def test_a_peak_term_network_trains_ships_and_loads_with_its_directions(tmp_path):
    """`hemicube train --peak-term` (mini rig, compact, 4 steps): the run's decoder carries the rig's LED directions;
    `network ship` keeps them in float32 beside the float16 matrices; the shipped network loads with them and
    re-scores to model.json's held-out loss."""
    import hemicube.cli
    from safetensors.torch import load_file

    from reconstruction.network.data import led_directions
    from reconstruction.network.shipped import load_shipped, score_network
    from reconstruction.network.train import TrainConfig, load_run_model

    run, dest = tmp_path / "run", tmp_path / "ship"
    assert hemicube.cli.main(["train", "--rig", "mini", "--architecture", "compact", "--peak-term", "--steps", "4",
                              "--eval-every", "2", "--no-progress", "-o", str(run)]) == 0
    rig = twin.load_rig("mini")
    assert np.array_equal(load_run_model(run).decoder.led_directions.numpy(), led_directions(rig))
    assert hemicube.cli.main(["network", "ship", str(run), "-o", str(dest)]) == 0
    tensors = load_file(str(dest / "model.safetensors"))
    assert tensors["decoder.led_directions"].dtype == torch.float32
    assert tensors["decoder.peak.0.weight"].dtype == torch.float16
    model, info = load_shipped(dest)
    assert info["config"]["peak_term"] is True
    assert np.array_equal(model.decoder.led_directions.numpy(), led_directions(rig))
    again = score_network(model, rig, TrainConfig.from_json(info["config"]))
    assert again["heldout_loss"] == pytest.approx(info["heldout_loss"], rel=1e-6)

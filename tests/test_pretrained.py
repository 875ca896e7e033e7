"""The pretrained mini-rig network that ships in the package."""
from __future__ import annotations

import numpy as np
import pytest

import twin
from reconstruction.pretrained import heldout_loss, load_pretrained, pretrained_info, pretrained_patterns
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

    from reconstruction.data import heldout_set
    from reconstruction.train import TrainConfig

    info = pretrained_info("mini")
    config = TrainConfig.from_json(info["config"])
    held = heldout_set(twin.load_rig("mini"), config.sampling, config.heldout_size, config.seed)
    logs = torch.log1p(held["target"].double())
    blind = float(((logs - logs.mean(dim=0)) ** 2).sum(dim=1).mean())
    assert info["heldout_loss"] < 0.5 * blind, (info["heldout_loss"], blind)


def test_shipped_patterns_are_the_capture_default_for_mini():
    rig = twin.load_rig("mini")
    learned = pretrained_patterns(rig)
    assert learned.levels.shape == (64, rig.num_leds, 3) and learned.names[:2] == ("learned_00+", "learned_00-")
    assert not np.any((learned.levels[0::2] > 0) & (learned.levels[1::2] > 0))  # a signed pair never overlaps
    assert np.all(learned.levels[:, rig.is_bottom] == 0)
    plan = build_patterns(rig)
    np.testing.assert_array_equal(plan.levels[:64], learned.levels)


def test_no_model_for_other_rigs():
    assert pretrained_patterns(twin.load_rig("paper")) is None
    with pytest.raises(FileNotFoundError, match="no pretrained network ships for rig 'paper'"):
        load_pretrained("paper")
    model, info = load_pretrained("mini")
    assert not model.training and info["num_upper_leds"] == 396

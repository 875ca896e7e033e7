"""The designer's verdict on two designs (twin.design.verdict): "real" only at Welch p < 0.05 over >= 3 seeds with
every network 2x below the measurement-blind predictor and its held-out curve flat; "not resolved", with the reason,
otherwise. Welch's test is checked against SciPy's own implementation of it."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from twin.design.verdict import NOT_RESOLVED, REAL, compare, compare_all, tail_change, welch_t_test


def _flat(loss: float, steps: int = 100) -> list[list[float]]:
    """A held-out curve that fell, then stayed flat over the last half of its steps."""
    return [[s, loss * (1 + max(0.0, 0.5 - s / steps))] for s in range(10, steps + 1, 10)]


def _row(name, losses, blind=1.0, curves=None):
    return {"design": name, "heldout_eq3_per_seed": list(losses), "blind_eq3": blind,
            "heldout_curve_per_seed": curves if curves is not None else [_flat(v) for v in losses]}


@pytest.mark.parametrize("a, b", [([0.10, 0.11, 0.12], [0.20, 0.22, 0.19]), ([1.0, 2.0, 3.0, 4.0], [2.5, 2.6]),
                                  ([0.3, 0.31, 0.29], [0.3, 0.32, 0.28])])
def test_welch_matches_scipy(a, b):
    t, dof, p = welch_t_test(a, b)
    ref = stats.ttest_ind(a, b, equal_var=False)
    assert t == pytest.approx(ref.statistic, rel=1e-12) and p == pytest.approx(ref.pvalue, rel=1e-10)
    va, vb = np.var(a, ddof=1) / len(a), np.var(b, ddof=1) / len(b)  # Welch-Satterthwaite, written out
    assert dof == pytest.approx((va + vb) ** 2 / (va ** 2 / (len(a) - 1) + vb ** 2 / (len(b) - 1)), rel=1e-12)


def test_a_clear_difference_is_real():
    v = compare(_row("a", [0.10, 0.11, 0.12]), _row("b", [0.30, 0.31, 0.29]))
    assert v["verdict"] == REAL and v["better"] == "a" and v["p"] < 0.05 and not v["why"]
    assert v["ratio"] == pytest.approx(0.30 / 0.11)
    assert v["text"].endswith(": real")


def test_overlapping_seeds_are_not_resolved():
    v = compare(_row("a", [0.10, 0.14, 0.12]), _row("b", [0.13, 0.11, 0.15]))
    assert v["verdict"] == NOT_RESOLVED and v["p"] >= 0.05
    assert any("Welch" in w for w in v["why"])


def test_networks_that_do_not_beat_the_blind_predictor_2x_are_not_resolved():
    """A clearly separated pair whose networks score within 2x of the blind predictor: it compares two networks
    that learned little of their photos, not two designs."""
    a, b = _row("a", [0.60, 0.61, 0.62]), _row("b", [0.90, 0.91, 0.89])
    v = compare(a, b)
    assert v["p"] < 0.05 and v["verdict"] == NOT_RESOLVED
    assert any("blind" in w and w.startswith("a'") for w in v["why"])
    assert any("blind" in w and w.startswith("b'") for w in v["why"])


def test_too_few_seeds_or_a_curve_still_falling_is_not_resolved():
    v = compare(_row("a", [0.10, 0.11]), _row("b", [0.30, 0.31]))
    assert v["verdict"] == NOT_RESOLVED and any("needs 3" in w for w in v["why"])
    falling = [[s, 0.3 * (2 - s / 100)] for s in range(10, 101, 10)]  # -> 0.3, still 12 % down over the last 20 %
    v = compare(_row("a", [0.10, 0.11, 0.12]), _row("b", [0.30, 0.31, 0.29], curves=[falling] * 3))
    assert v["verdict"] == NOT_RESOLVED and any("train longer" in w for w in v["why"])
    coarse = [[[100, 0.3]]] * 3  # one evaluation: cannot tell
    v = compare(_row("a", [0.10, 0.11, 0.12]), _row("b", [0.30, 0.31, 0.29], curves=coarse))
    assert v["verdict"] == NOT_RESOLVED and any("too coarse" in w for w in v["why"])


def test_tail_change_reads_the_last_fifth_of_the_steps():
    assert tail_change([[10, 2.0], [80, 1.0], [100, 0.99]]) == pytest.approx(0.01)
    assert tail_change([[100, 1.0]]) is None
    assert tail_change([[90, 1.0], [100, 0.9]]) is None  # nothing at or before 80 % of the steps


def test_every_pair_gets_a_verdict():
    rows = [_row("a", [0.1, 0.11, 0.12]), _row("b", [0.3, 0.31, 0.29]), _row("c", [0.31, 0.3, 0.29])]
    got = compare_all(rows)
    assert [(v["better"], v["worse"]) for v in got[:2]] == [("a", "b"), ("a", "c")]
    assert {got[2]["better"], got[2]["worse"]} == {"b", "c"}
    assert got[0]["verdict"] == REAL and got[2]["verdict"] == NOT_RESOLVED

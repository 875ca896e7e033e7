"""GGX fitting (reconstruction.stages.fitting): recovery of known texels from noise-free targets rendered by the
twin's forward model, the export convention, the neural method, input checks and determinism.

Targets are built here from the definition of network units (reconstruction.network.data: physical lumitexels of
the upper LEDs times LUMITEXEL_SCALE, checked against reconstruction.network.data.synthesize) and the linear
lights' upper-LED weights, for known parameters: the independent truth the fit must find again.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

import twin
from reconstruction.network.data import LUMITEXEL_SCALE, synthesize
from reconstruction.stages.fitting import direct, geometry, problem, solver
from reconstruction.stages.fitting import FitConfig, FitResult, fit_ggx, fit_method, to_maps
from reconstruction.stages.fitting.config import GEOMETRY_SIZE
from twin.capture.pattern_sets import linear_lights
from twin.materials.samples import SVBRDFMaps, read_maps, write_maps


def _tilt(deg, azimuth_deg):
    a, b = np.radians(deg), np.radians(azimuth_deg)
    return [np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)]


# (normal, tangent angle about n from +x carried along (deg), alpha_x, alpha_y, rho_d RGB, rho_s RGB):
# roughness 0.08-0.35 (lobes wide enough for the mini rig's 396 LEDs), tilts up to 25 deg, coloured and
# grey albedos, three anisotropic texels (one with alpha_x < alpha_y, which the export must swap).
MATERIALS = [
    (_tilt(0, 0), 0, 0.15, 0.15, (0.5, 0.5, 0.5), (2.0, 2.0, 2.0)),
    (_tilt(20, 30), 0, 0.25, 0.25, (0.3, 0.3, 0.3), (4.0, 4.0, 4.0)),
    (_tilt(10, 200), 40, 0.10, 0.35, (0.6, 0.3, 0.1), (1.5, 1.5, 1.5)),
    (_tilt(0, 0), 0, 0.3, 0.3, (0.6, 0.6, 0.6), (2.0, 2.0, 2.0)),
    (_tilt(15, 120), 70, 0.3, 0.08, (0.1, 0.1, 0.1), (6.0, 5.0, 4.0)),
    (_tilt(5, 300), 0, 0.12, 0.12, (0.2, 0.5, 0.7), (3.0, 3.0, 3.0)),
    (_tilt(25, 250), 0, 0.2, 0.2, (0.4, 0.4, 0.4), (2.0, 2.0, 2.0)),
    (_tilt(0, 0), 120, 0.35, 0.12, (0.25, 0.25, 0.25), (5.0, 5.0, 5.0)),
    (_tilt(12, 60), 0, 0.08, 0.08, (0.05, 0.05, 0.05), (8.0, 8.0, 8.0)),
]
GRID = (3, 3)
SIZE_MM = 90.0


def _truth():
    """The 9 texels at the centres of a 3 x 3 grid of 30 mm texels (row i along +y, column j along +x)."""
    c = (np.arange(3) - 1) * 30.0
    pos = np.array([[x, y, -122.0] for y in c for x in c])
    n = np.array([m[0] for m in MATERIALS], float)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = []
    for ni, m in zip(n, MATERIALS):  # +x carried along to the tilted normal, then turned about it
        t0 = np.array([1.0, 0, 0]) - ni * ni[0]
        t0 /= np.linalg.norm(t0)
        th = np.radians(m[1])
        t.append(np.cos(th) * t0 + np.sin(th) * np.cross(ni, t0))
    return {"position": pos, "normal": n, "tangent": np.array(t), "alpha_x": np.array([m[2] for m in MATERIALS]),
            "alpha_y": np.array([m[3] for m in MATERIALS]), "rho_d": np.array([m[4] for m in MATERIALS]),
            "rho_s": np.array([m[5] for m in MATERIALS])}


def _targets(rig, p, device="cpu"):
    """Network-unit lumitexels (N, L_upper, 3) and linear-light measurements (N, 64, 3) of params p."""
    upper = np.flatnonzero(~rig.is_bottom)
    m = twin.lumitexels(rig, p["position"], p["normal"], p["tangent"], p["rho_d"], p["rho_s"], p["alpha_x"],
                        p["alpha_y"], convention="physical", camera="primary", device=device,
                        transparency=np.zeros(len(p["position"])),
                        visibility=True)[:, upper] * LUMITEXEL_SCALE
    w = linear_lights(rig).weights[:, upper].astype(np.float32)
    return m.astype(np.float32), np.einsum("plc,klc->pkc", m, w).astype(np.float32), w


def weak_beside_glossy(rig, grid_shape, size_mm: float, weak_columns: int, weak_alpha_y: float):
    """Flat texels of an R x C grid over size_mm: the first `weak_columns` columns a rough, weak lobe on a bright
    diffuse (paper stock: alpha_x 0.45, alpha_y `weak_alpha_y`, rho_s 0.3 on rho_d 0.8), the rest a glossy dark ink
    (alpha 0.12, rho_s 3 on rho_d 0.1). Returns (parameters, the weak texels' mask)."""
    from twin.materials.samples import grid_positions

    R, C = grid_shape
    pos = grid_positions(size_mm, (R, C), rig.sample).reshape(-1, 3)
    weak = np.repeat(np.arange(C)[None] < weak_columns, R, 0).ravel()
    n = len(pos)
    return {"position": pos, "normal": np.tile([0.0, 0.0, 1.0], (n, 1)), "tangent": np.tile([1.0, 0.0, 0.0], (n, 1)),
            "alpha_x": np.where(weak, 0.45, 0.12), "alpha_y": np.where(weak, weak_alpha_y, 0.12),
            "rho_d": np.where(weak[:, None], 0.8, 0.1) * np.ones((n, 3)),
            "rho_s": np.where(weak, 0.3, 3.0)[:, None] * np.ones((n, 3))}, weak


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def fitted(mini):
    truth = _truth()
    m, lines, w = _targets(mini, truth)
    # the defaults (Levenberg-Marquardt, 20 iterations; Adam's 60 steps left 13% alpha on the slowest of these
    # texels and needed 120 for 0.6%)
    res = fit_ggx(mini, truth["position"], m, lines=lines, line_weights=w, config=FitConfig())
    return truth, (m, lines, w), res


def test_targets_are_network_units(mini, fitted):
    """The targets built here are what the acquisition network sees: synthesize gives their grey mean."""
    truth, (m, _, _), _ = fitted
    grey = synthesize(mini, {k: torch.as_tensor(v, dtype=torch.float32) for k, v in truth.items()}, "primary")
    np.testing.assert_allclose(grey.numpy(), m.mean(-1), rtol=1e-5, atol=1e-6)


def test_recovers_known_texels(fitted):
    """Noise-free targets from the same forward model: the only error left is the optimiser's, so the
    tolerances (1 deg, 5% alpha, 5% rho; measured <= 0.02 deg, 0.6%, 0.5%) leave a >= 8x margin."""
    truth, _, r = fitted
    assert isinstance(r, FitResult)
    for k in ("normal", "tangent", "rho_d", "rho_s"):
        assert getattr(r, k).shape == (9, 3) and getattr(r, k).dtype == np.float32
    angle = np.degrees(np.arccos(np.clip((r.normal.astype(np.float64) * truth["normal"]).sum(1), -1, 1)))
    assert angle.max() < 1.0, angle
    # alpha up to the (alpha_x, alpha_y, t) <-> (alpha_y, alpha_x, n x t) symmetry: compare sorted pairs
    fit_a = np.sort(np.stack([r.alpha_x, r.alpha_y], 1), 1)
    true_a = np.sort(np.stack([truth["alpha_x"], truth["alpha_y"]], 1), 1)
    assert np.abs(fit_a / true_a - 1).max() < 0.05
    assert np.abs(r.rho_d / truth["rho_d"] - 1).max() < 0.05
    assert np.abs(r.rho_s / truth["rho_s"] - 1).max() < 0.05
    assert r.history[-1] < 1e-3 * r.history[0]
    assert r.info["texel_loss"].shape == (9,) and r.info["seconds_per_iteration"] > 0


def test_export_canonical_anisotropy_and_tangent(fitted):
    """to_maps: alpha_x >= alpha_y everywhere; where the truth is anisotropic the exported tangent is its
    larger-roughness axis modulo pi (texel 2 has alpha_x < alpha_y, so that axis is n x t)."""
    truth, _, r = fitted
    maps = to_maps(r, GRID, SIZE_MM, name="fit")
    assert isinstance(maps, SVBRDFMaps)
    assert np.all(maps.alpha[..., 0] >= maps.alpha[..., 1])
    assert np.all(maps.normal[..., 2] > 0)
    axis = np.where((truth["alpha_x"] >= truth["alpha_y"])[:, None], truth["tangent"],
                    np.cross(truth["normal"], truth["tangent"]))
    aniso = np.maximum(truth["alpha_x"], truth["alpha_y"]) / np.minimum(truth["alpha_x"], truth["alpha_y"]) >= 1.5
    assert aniso.sum() == 3
    cos = np.abs((maps.tangent.reshape(9, 3).astype(np.float64) * axis).sum(1))
    assert np.degrees(np.arccos(np.clip(cos[aniso], 0, 1))).max() < 1.0


def test_maps_round_trip(fitted, tmp_path):
    _, _, r = fitted
    beta = np.linspace(0, 1, 9).reshape(GRID)
    maps = to_maps(r, GRID, SIZE_MM, transparency=beta, name="fit")
    back = read_maps(write_maps(maps, tmp_path / "maps"))
    assert back.name == "fit" and back.size_mm == SIZE_MM
    for k in SVBRDFMaps.ARRAYS:
        np.testing.assert_allclose(getattr(back, k), getattr(maps, k), atol=1e-6, err_msg=k)
    with pytest.raises(ValueError, match="texels"):
        to_maps(r, (2, 4), SIZE_MM)
    with pytest.raises(ValueError, match="transparency"):
        to_maps(r, GRID, SIZE_MM, transparency=np.zeros((2, 2)))


def test_neural_method_lowers_its_loss(mini, fitted):
    """The feature texture + 5 heads: after its warm start, Adam on random texel batches lowers the loss
    over all texels (the same seed, so both runs start from the same network)."""
    truth, (m, lines, w), _ = fitted
    cfg = FitConfig(method="neural", iterations=0, batch=9, warm_start_steps=100, features=8, hidden=32)
    start = fit_ggx(mini, truth["position"], m, lines=lines, line_weights=w, grid_shape=GRID, config=cfg)
    end = fit_method(mini, truth["position"], m, method="neural", lines=lines, line_weights=w, grid_shape=GRID,
                     config=FitConfig(method="neural", iterations=60, batch=9, warm_start_steps=100, features=8,
                                      hidden=32, lr=3e-3))
    assert end.info["method"] == "neural" and len(end.history) == 60
    assert end.info["texel_loss"].mean() < 0.5 * start.info["texel_loss"].mean()
    assert end.normal.shape == (9, 3) and np.all(end.normal[:, 2] > 0)


def test_deterministic(mini, fitted):
    truth, (m, lines, w), _ = fitted
    for cfg in (FitConfig(iterations=5, seed=3),
                FitConfig(method="neural", iterations=5, batch=4, warm_start_steps=5, features=4, hidden=8, seed=3)):
        a, b = (fit_ggx(mini, truth["position"], m, lines=lines, line_weights=w, grid_shape=GRID, config=cfg)
                for _ in range(2))
        for k in ("normal", "tangent", "alpha_x", "alpha_y", "rho_d", "rho_s"):
            assert np.array_equal(getattr(a, k), getattr(b, k)), (cfg.method, k)
        assert a.history == b.history


@pytest.mark.parametrize("loss", ["log1p", "mse"])
def test_a_lumitexel_source_fits_as_the_array_does(mini, fitted, loss):
    """fit_ggx with a lumitexel source (a function of texel indices, asked chunk by chunk; what the pipeline passes,
    reconstruction.stages.finetune.decoded_lumitexels) gives the array's result to the bit, on a grid with the joint prior
    and with chunks smaller than the problem; a source's bad lumitexels get the array's errors."""
    truth, (m, lines, w), _ = fitted
    asked = []

    def source(idx):
        asked.append(idx.numel())
        return torch.as_tensor(m)[idx]

    cfg = FitConfig(iterations=6, batch=4, loss=loss)
    a, b = (fit_ggx(mini, truth["position"], x, lines=lines, line_weights=w, grid_shape=GRID, config=cfg)
            for x in (m, source))
    for k in ("normal", "tangent", "alpha_x", "alpha_y", "rho_d", "rho_s"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert a.history == b.history and max(asked) <= 4
    for bad, message in ((lambda idx: torch.as_tensor(m)[idx][:, :-1], "L_upper"),
                         (lambda idx: -torch.as_tensor(m)[idx], ">= 0"),
                         (lambda idx: torch.full((idx.numel(), m.shape[1], 3), np.nan), "lumitexels contains NaN"),
                         (lambda idx: _one_bad(torch.as_tensor(m)[idx], np.nan), "lumitexels contains NaN"),
                         (lambda idx: _one_bad(torch.as_tensor(m)[idx], np.inf), "lumitexels contains NaN or Inf"),
                         (lambda idx: _one_bad(torch.as_tensor(m)[idx], -np.inf), "lumitexels contains NaN or Inf")):
        with pytest.raises(ValueError, match=message):
            fit_ggx(mini, truth["position"], bad, lines=lines, line_weights=w, config=cfg)


def _one_bad(m: torch.Tensor, value: float) -> torch.Tensor:
    """m with one value set to `value` (a source's chunk that the quick min/max check must not pass)."""
    m = m.clone()
    m[-1, 3, 1] = value
    return m


def test_bad_inputs(mini, fitted):
    truth, (m, lines, w), _ = fitted
    pos = truth["position"]
    bad = m.copy()
    bad[2, 5, 1] = np.nan
    with pytest.raises(ValueError, match="lumitexels contains NaN"):
        fit_ggx(mini, pos, bad)
    with pytest.raises(ValueError, match="positions contains NaN or Inf"):
        fit_ggx(mini, np.where(np.arange(9)[:, None] == 4, np.inf, pos), m)
    with pytest.raises(ValueError, match="L_upper"):
        fit_ggx(mini, pos, m[:, :-1])
    with pytest.raises(ValueError, match="L_upper"):
        fit_ggx(mini, pos[:5], m)
    with pytest.raises(ValueError, match=">= 0"):
        fit_ggx(mini, pos, -m)
    with pytest.raises(ValueError, match="give both or neither"):
        fit_ggx(mini, pos, m, lines=lines)
    with pytest.raises(ValueError, match="lines must have shape"):
        fit_ggx(mini, pos, m, lines=lines[:, :10], line_weights=w)
    with pytest.raises(ValueError, match="line_weights must have shape"):
        fit_ggx(mini, pos, m, lines=lines, line_weights=w[:, :10])
    with pytest.raises(ValueError, match="grid_shape"):
        fit_ggx(mini, pos, m, config=FitConfig(method="neural"))
    with pytest.raises(ValueError, match="grid_shape"):
        fit_ggx(mini, pos, m, grid_shape=(2, 2), config=FitConfig(method="neural"))
    with pytest.raises(ValueError, match="no camera"):
        fit_ggx(mini, pos, m, config=FitConfig(camera="nope"))
    for kw in ({"method": "lbfgs"}, {"loss": "l1"}, {"iterations": -1}, {"batch": 0}, {"lr": 0.0},
               {"alpha_range": (0.5, 0.1)}, {"rho_s_max": 50.0}, {"lambda_lines": -1.0}, {"jacobian": "central"},
               {"precision": "bf16"}):
        with pytest.raises(ValueError, match="FitConfig"):
            FitConfig(**kw)


def test_roughness_tensor_coordinates_round_trip():
    """_to_tensor / _from_tensor (the joint prior's coordinates): the same lobe back, as (theta, alpha_x,
    alpha_y) or its 90-degree turn with the alphas swapped; an isotropic lobe is d = 0 whatever theta."""
    from reconstruction.stages.fitting.geometry import _from_tensor, _to_tensor

    g = torch.Generator().manual_seed(3)
    q = torch.cat([torch.randn(64, 2, generator=g) * 0.2, torch.rand(64, 1, generator=g) * 6 - 3,
                   torch.log(torch.rand(64, 2, generator=g) * 0.9 + 0.01)], 1).double()
    back = _from_tensor(_to_tensor(q))
    assert torch.allclose(back[:, :2], q[:, :2])
    same = torch.allclose(back[:, 3:], q[:, 3:], atol=1e-9)
    swapped = q[:, 3] < q[:, 4]
    np.testing.assert_allclose(torch.where(swapped[:, None], q[:, [4, 3]], q[:, 3:]).numpy(), back[:, 3:].numpy(),
                               atol=1e-9)
    turn = torch.where(swapped, q[:, 2] + np.pi / 2, q[:, 2])
    np.testing.assert_allclose(torch.cos(2 * (turn - back[:, 2])).numpy(), 1.0, atol=1e-9)  # the axis, mod pi
    assert not same  # some of these were swapped: the canonical order is part of the round trip
    iso = _to_tensor(torch.tensor([[0.0, 0.0, 1.3, -1.0, -1.0]], dtype=torch.float64))
    assert float(iso[0, 3].abs() + iso[0, 4].abs()) == 0.0


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_frame_derivatives_match_forward_mode_autodiff(dtype, tol):
    """_frame_derivatives' closed form (the analytic Jacobian's input) against torch.func.jacfwd of _frame_of on
    a tilted sample frame, every tangent angle and tilts to ~30 degrees; the log alphas move no row."""
    from types import SimpleNamespace

    g = torch.Generator().manual_seed(5)
    N = geometry._unit(torch.tensor([0.1, -0.2, 1.0], dtype=torch.float64))
    X = geometry._unit(torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), N, dim=-1))
    frame = torch.stack([N, X, torch.linalg.cross(N, X, dim=-1)]).to(dtype)
    q = (torch.randn(200, 5, generator=g, dtype=torch.float64) * torch.tensor([0.4, 0.4, 2.0, 0.5, 0.5],
                                                                              dtype=torch.float64)).to(dtype)
    geom, d_frame, d_log_alpha = geometry._frame_derivatives(SimpleNamespace(frame=frame), q)

    def rows(g3):
        f = geometry._frame_of(g3[None], frame)
        return torch.stack([f["tangent"], torch.linalg.cross(f["normal"], f["tangent"], dim=-1), f["normal"]], 1)[0]

    ref = torch.stack([torch.func.jacfwd(rows)(q[i, :3]) for i in range(q.shape[0])]).permute(0, 3, 1, 2)
    assert float((d_frame[:, :3] - ref).abs().max()) < tol
    assert not d_frame[:, 3:].any()
    assert torch.equal(d_log_alpha[:, 3:], torch.eye(2, dtype=dtype).expand(200, 2, 2))
    f = geometry._frame_of(q, frame)
    assert torch.equal(geom["normal"], f["normal"]) and torch.equal(geom["tangent"], f["tangent"])


def test_joint_prior_pools_a_weak_lobe_and_keeps_a_clear_one(mini, device):
    """A 6 x 8 grid: a rough, weak lobe on a bright diffuse (paper stock: the lobe is ~1% of a line photo)
    next to a glossy ink of another colour, lines with 0.4% seeded photo noise (the extracted lines' level,
    docs/accuracy.md) and lumitexels with 2%. Each texel alone errs on the weak lobe's alpha; the joint prior (FitConfig.alpha_prior)
    pools its photos and meets the 10% goal there, while the glossy texels keep their own alpha (the prior
    does not reach across the change of colour)."""
    R, C = 6, 8
    p, weak = weak_beside_glossy(mini, (R, C), 60.0, 5, 0.45)
    pos = p["position"]
    m, lines, w = _targets(mini, p, device)
    rng = np.random.default_rng(7)
    noisy = lines * (1 + 0.004 * rng.standard_normal(lines.shape)).astype(np.float32)
    m = m * (1 + 0.02 * rng.standard_normal(m.shape)).astype(np.float32)  # a decoder's error, ~2%

    trials, pinned = [], []

    def errors(prior):  # |log alpha| and relative rho_s errors per texel
        r = fit_ggx(mini, pos, m, lines=noisy, line_weights=w, grid_shape=(R, C),
                    config=FitConfig(alpha_prior=prior, device=device))
        trials.extend(r.info.get("joint_trials", []))
        pinned.append(r.info.get("joint_pinned"))
        return (np.abs(np.log(np.sqrt(r.alpha_x * r.alpha_y) / np.sqrt(p["alpha_x"] * p["alpha_y"]))),
                np.abs(r.rho_s.mean(1) / p["rho_s"].mean(1) - 1))

    # measured: alone 0.149 / 52% on the weak lobe; tau 0.1 (the default) 0.104 / 34%; tau 0.05 0.056 / 16%;
    # the glossy texels 0.0013 / 0.1% in all three
    (alone, rs_alone), (joint, rs_joint) = errors(None), errors(0.05)
    assert np.median(alone[weak]) > 0.1  # the texels alone miss the goal ...
    assert np.median(joint[weak]) < 0.1 and np.median(joint[weak]) < 0.5 * np.median(alone[weak])  # ... pooled
    assert np.median(rs_joint[weak]) < 0.5 * np.median(rs_alone[weak])
    assert np.median(joint[~weak]) < 0.02 and np.max(np.abs(joint[~weak] - alone[~weak])) < 0.01
    assert np.median(rs_joint[~weak]) < 0.01
    # the glossy texels' photos pin their roughness (joint._pinned): the joint prior leaves them, and only them
    assert pinned == [None, int((~weak).sum())]
    # each trial: [median damping of the free texels, relative change of F, share of them whose model held]
    assert len(trials) >= 3 and trials[0][0] == FitConfig().lm_damping and all(len(t) == 3 for t in trials)
    assert any(change < 0 for _, change, _ in trials) and all(0 <= held <= 1 for _, _, held in trials)


def test_a_refit_fits_again_only_the_texels_whose_photos_changed(mini, monkeypatch):
    """_fit_direct's start (the pipeline's refit of the texels next to a brighter highlight): after the photos of
    some texels change, only those go through the initial candidates and Levenberg-Marquardt again, and the refit
    ends where a whole fit of the new photos ends (each texel's own fit depends on its own photos; propagation and
    the joint prior run over all). A 4 x 6 grid of paper stock beside a glossy ink, photos with 0.4% seeded noise;
    then the stock's first column gets a glossier lobe's photos (alpha_y 0.2 instead of 0.45)."""
    R, C = 4, 6
    p, weak = weak_beside_glossy(mini, (R, C), 40.0, 3, 0.45)
    m, lines, w = _targets(mini, p)
    noise = (1 + 0.004 * np.random.default_rng(11).standard_normal(lines.shape)).astype(np.float32)
    redo = np.repeat(np.arange(C)[None] == 0, R, 0).ravel()
    p2 = {**p, "alpha_y": np.where(redo, 0.2, p["alpha_y"])}
    m2, lines2, _ = _targets(mini, p2)
    cfg = FitConfig(alpha_prior=0.05)
    first = fit_ggx(mini, p["position"], m, lines=lines * noise, line_weights=w, grid_shape=(R, C), config=cfg)
    whole = fit_ggx(mini, p["position"], m2, lines=lines2 * noise, line_weights=w, grid_shape=(R, C), config=cfg)
    sizes, initial = [], direct._initial

    def spy(part):
        sizes.append(part.n)
        return initial(part)

    monkeypatch.setattr(direct, "_initial", spy)
    refit = fit_ggx(mini, p["position"], m2, lines=lines2 * noise, line_weights=w, grid_shape=(R, C), config=cfg,
                    start=(first.info["texel_q"], redo))
    assert sizes == [int(redo.sum())]
    # float32 products of other chunk sizes round differently (~1e-5); a texel left at its old numbers would be off
    # by the change of its roughness, log(0.45 / 0.2) / 2 = 0.4 in the mean log alpha
    np.testing.assert_allclose(refit.info["texel_q"], whole.info["texel_q"], rtol=0, atol=1e-3)
    for k in ("alpha_x", "alpha_y", "rho_s", "normal"):
        np.testing.assert_allclose(getattr(refit, k), getattr(whole, k), rtol=1e-3, atol=1e-4, err_msg=k)
    # a refit's state saved before refits kept the other texels' numbers (its chunks covered every texel; none done)
    # is not resumed, which would leave those texels at zero: the refit starts again and gives the same numbers
    class Saved:
        def __init__(self, state):
            self.state = state

        def load(self):
            return self.state

        def save(self, state):
            self.state = state

    old = Saved({"phase": "chunks", "chunks_done": 0, "q": np.zeros((R * C, GEOMETRY_SIZE), np.float32),
                 "history": np.zeros(cfg.steps), "restarted": [],
                 "seconds": {"init": 0.0, "iterations": 0.0, "propagation": 0.0, "joint": 0.0}})
    resumed = fit_ggx(mini, p["position"], m2, lines=lines2 * noise, line_weights=w, grid_shape=(R, C), config=cfg,
                      start=(first.info["texel_q"], redo), checkpoint=old)
    np.testing.assert_array_equal(resumed.info["texel_q"], refit.info["texel_q"])
    np.testing.assert_array_equal(resumed.alpha_x, refit.alpha_x)
    assert old.state["refitted"] == int(redo.sum())
    # unchanged photos: nothing to fit again, nothing moves
    again = fit_ggx(mini, p["position"], m, lines=lines * noise, line_weights=w, grid_shape=(R, C), config=cfg,
                    start=(first.info["texel_q"], np.zeros(R * C, bool)))
    np.testing.assert_allclose(again.alpha_x, first.alpha_x, rtol=1e-4)
    with pytest.raises(ValueError, match="refit's start"):
        fit_ggx(mini, p["position"], m, lines=lines, line_weights=w, grid_shape=(R, C), config=cfg,
                start=(first.info["texel_q"][:-1], redo))


def test_pinned_texels_are_those_whose_roughness_the_photos_fix_to_a_quarter_of_tau():
    """joint._pinned against the closed form: the variance of the mean log alpha m is the [m, m] entry of the
    inverse of the texel's 5 x 5 information matrix (every other number free); pinned where its square root is
    under tau / 4."""
    from reconstruction.stages.fitting.joint import _pinned

    rng = np.random.default_rng(3)
    G = rng.standard_normal((400, 5, 12))
    H = G @ G.transpose(0, 2, 1) * np.exp(rng.uniform(-2, 9, (400, 1, 1)))  # SPD, var(m) over 1e-5 .. 1e1
    var = np.linalg.inv(H)[:, 2, 2]
    tau = 0.1
    got = _pinned(torch.as_tensor(H), tau).numpy()
    far = np.abs(np.sqrt(var) / (tau / 4) - 1) > 1e-6
    assert np.array_equal(got[far], (np.sqrt(var) < tau / 4)[far]) and 0 < got.sum() < len(got)
    assert not _pinned(torch.zeros(1, 5, 5, dtype=torch.float64), tau).any()  # a texel its photos say nothing of


def test_diffuse_normal_finds_a_steep_tilt(mini):
    """_diffuse_normal (photometric stereo on the LEDs below the highlight, an initial candidate): texels
    tilted 35-50 deg, narrow and broad lobes, exact targets: within 1 deg of the true normal; the half vector of
    the brightest LED (_peak_normal) is not (for these the mirror direction leaves the LED dome)."""
    from reconstruction.stages.fitting.candidates import _diffuse_normal, _peak_normal
    from reconstruction.stages.fitting.problem import _problem

    tilts = [(35, 20), (40, 100), (45, 200), (50, 300), (45, 0), (50, 150)]
    n = len(tilts)
    p = {"position": np.array([[x, 0.0, -122.0] for x in np.linspace(-30, 30, n)]),
         "normal": np.array([_tilt(t, a) for t, a in tilts]), "tangent": None,
         "alpha_x": np.array([0.03, 0.3, 0.05, 0.1, 0.02, 0.2]), "alpha_y": np.array([0.03, 0.3, 0.05, 0.1, 0.02, 0.2]),
         "rho_d": np.full((n, 3), 0.5), "rho_s": np.full((n, 3), 3.0)}
    p["normal"] /= np.linalg.norm(p["normal"], axis=1, keepdims=True)
    t0 = np.cross(p["normal"], [0.0, 1.0, 0.0])
    p["tangent"] = t0 / np.linalg.norm(t0, axis=1, keepdims=True)
    m, lines, w = _targets(mini, p)
    prob = _problem(mini, p["position"], m, lines, w, None, FitConfig())
    truth = torch.as_tensor(p["normal"], dtype=torch.float32)

    def deg(v):
        return np.degrees(np.arccos(np.clip((v * truth).sum(1).numpy(), -1, 1)))

    assert deg(_diffuse_normal(prob)).max() < 1.0
    assert deg(_peak_normal(prob)).max() > 5.0


def test_propagation_restarts_in_chunks(mini, fitted, monkeypatch):
    """Neighbour propagation restarts its texels in the fit's chunks (AUTO_CHUNK_PAIRS texel-LED pairs), as every
    other pass runs: paper stock at 1024^2 restarted so many texels that one Levenberg-Marquardt over all of them
    asked for more memory than a GPU has. The chunks restart the same texels to the same numbers."""
    truth, (m, lines, w), _ = fitted
    prob = problem._problem(mini, truth["position"], m, lines, w, GRID, FitConfig(iterations=3), None)
    rng = np.random.default_rng(3)  # scattered numbers: many texels find a neighbour's better and restart
    q = torch.as_tensor(rng.normal(0.0, 0.5, (prob.n, GEOMETRY_SIZE)), dtype=prob.pos.dtype)
    sizes, lm = [], solver._levenberg_marquardt

    def spy(part, q0, history):
        sizes.append(part.n)
        return lm(part, q0, history)

    monkeypatch.setattr(solver, "_levenberg_marquardt", spy)
    whole, moved, _ = solver._propagate(prob, q.clone(), GRID)
    assert sizes == [moved] and moved >= 3
    monkeypatch.setattr(problem, "AUTO_CHUNK_PAIRS", 2 * prob.leds)
    sizes.clear()
    chunked, moved_chunked, _ = solver._propagate(prob, q.clone(), GRID)
    assert moved_chunked == moved and max(sizes) == 2 and sum(sizes) == moved
    # float32 products of other sizes round differently (measured: 9e-6 at most); a texel written back to the wrong
    # place would be off by the numbers' own scale, ~0.5
    np.testing.assert_allclose(chunked.numpy(), whole.numpy(), rtol=0, atol=1e-3)


def test_a_later_propagation_round_tries_only_what_changed_and_decides_as_a_whole_round(mini, fitted, monkeypatch):
    """A round after the first tries only the texels the round before restarted and their 4 neighbours (the others
    would compare the numbers that round compared): it restarts the same texels to the same numbers as a round
    over every texel, and evaluates far fewer. A 6 x 6 grid of the fitted texels, three of them scrambled."""
    truth, (m, lines, w), res = fitted
    R, C = 6, 6
    tile = np.arange(R * C) % len(m)
    prob = problem._problem(mini, truth["position"][tile], m[tile], lines[tile], w, (R, C), FitConfig(iterations=3),
                            None)
    n, t = (torch.as_tensor(getattr(res, k)[tile], dtype=prob.pos.dtype) for k in ("normal", "tangent"))
    N, X, Y = prob.frame
    t0 = geometry._base_tangent(n, prob.frame)
    theta = torch.atan2((torch.linalg.cross(n, t0, dim=-1) * t).sum(-1), (t0 * t).sum(-1))
    q = torch.stack([(n @ X) / (n @ N), (n @ Y) / (n @ N), theta,
                     *(torch.log(torch.as_tensor(getattr(res, k)[tile], dtype=prob.pos.dtype))
                       for k in ("alpha_x", "alpha_y"))], 1)
    q[[7, 20, 33]] = torch.as_tensor(np.random.default_rng(4).normal(0.0, 0.5, (3, 5)), dtype=q.dtype)
    q1, moved1, changed = solver._propagate(prob, q.clone(), (R, C))
    assert moved1 >= 1 and int(changed.sum()) == moved1
    tried, losses = [], solver._losses

    def spy(prob_, x, texels=None):
        tried.append(x.shape[0])
        return losses(prob_, x, texels)

    monkeypatch.setattr(solver, "_losses", spy)
    whole, moved_whole, mask_whole = solver._propagate(prob, q1.clone(), (R, C))
    assert tried == [prob.n] * 5
    tried.clear()
    part, moved_part, mask_part = solver._propagate(prob, q1.clone(), (R, C), changed)
    grid = changed.reshape(R, C)
    near = grid.clone()
    near[1:] |= grid[:-1]
    near[:-1] |= grid[1:]
    near[:, 1:] |= grid[:, :-1]
    near[:, :-1] |= grid[:, 1:]
    assert tried == [int(near.sum())] * 5 and int(near.sum()) < prob.n
    assert moved_part == moved_whole and torch.equal(mask_part, mask_whole)
    np.testing.assert_allclose(part.numpy(), whole.numpy(), rtol=0, atol=1e-3)

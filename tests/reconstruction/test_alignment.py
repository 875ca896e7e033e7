"""Two-view alignment (reconstruction/stages/alignment.py), scored against independent truth: the twin's ground-truth
pixel -> texel sidecars for a mini-rig capture, and synthetic pairs whose true mapping is known in closed form
(an analytic texture shifted or warped by a known homography)."""
from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

import twin
from reconstruction.stages.alignment import AlignConfig, AlignmentError, align_views, alignment_error, warp_to_primary
from reconstruction.stages.patchmatch import PatchCost, exhaustive, patchmatch, subpixel
from twin.rig.camera import Camera

GOAL_PX = 0.5  # the goal: median alignment error <= 0.5 px (docs/accuracy.md)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _uniform_pair(seed: int):
    """The two uniform-light photos (k = 129) of a mini-rig capture of the ramps sample (the main job's) at capture
    seed `seed`, taken by twin.capture.runner's photo loop (only these two photos, to stay fast), with the
    sidecars: the same photos as a whole capture at that seed."""
    from twin.capture.plan import build_patterns, paper_plan
    from twin.capture.runner import open_backends, photos
    from twin.materials.samples import load_sample

    rig = twin.load_rig("mini")
    patterns = build_patterns(rig)
    todo = [p for p in paper_plan(rig, patterns) if p.pattern == "uniform"]
    with open_backends(rig, load_sample("ramps", resolution=128), "sim", seed, "cpu") as sims:
        shots = {photo.camera: hdr["radiance"].numpy() for photo, _, hdr, _ in photos(rig, sims, patterns, todo,
                                                                                      "cpu")}
        truth = {cam: sims["sample"].surfaces(cam).pixel_texel().astype(np.float32) for cam in shots}
    return rig, shots, truth


@pytest.fixture(scope="module")
def mini_uniform():
    return _uniform_pair(1)


def _align(mini_uniform, **kw):
    rig, photos, truth = mini_uniform
    al = align_views(photos["primary"], photos["secondary"], rig, AlignConfig(**kw))
    return al, alignment_error(al, truth["primary"], truth["secondary"])


def test_default_config_meets_the_goal_on_a_mini_capture(mini_uniform):
    al, err = _align(mini_uniform)
    assert err["median_px"] <= GOAL_PX, err
    assert err["p90_px"] <= 2 * GOAL_PX, err
    assert err["count"] > 12000 and err["off_sample"] < 50, err  # the sample covers ~13,600 primary pixels
    assert al.map.shape == (192, 222, 2) and al.map.dtype == np.float32
    # SIFT looks inside the frame's window only, where the mini rig's 222-px photos of this sample give too few
    # matches: "auto" goes on to the markers, and the dense step refits from them
    assert al.info["method"] == "markers" and "sift" in al.info["coarse_failed"]
    assert al.info["dense"]["refit"][0]["applied"]


def test_sift_is_not_fitted_to_the_holder_frame(mini_uniform):
    """Before SIFT was kept to the frame's window, its ~20 matches all lay on the frame's markers, 1.5 mm above the
    sample: a homography of the frame's plane, 1-3 px off on the mini rig, 10-22 px on the paper rig (the
    failure on glossy, weakly textured samples there). Now it finds too few matches and says so."""
    with pytest.raises(AlignmentError, match="sift: only"):
        _align(mini_uniform, coarse="sift", dense=False)


def test_auto_passes_over_a_coarse_homography_far_from_the_calibration(mini_uniform, monkeypatch):
    """A measured homography that moves the window's corners farther from the calibrated geometry than
    AlignConfig.coarse_tolerance is not used: "auto" says why and takes the next method."""
    import reconstruction.stages.alignment as A

    rig, photos, truth = mini_uniform
    real = A._coarse

    def shifted_markers(g0, g1, cam0, cam1, rig_, cfg, scale):
        H, info = real(g0, g1, cam0, cam1, rig_, cfg, scale)
        if cfg.coarse == "markers":  # the markers' homography, 12 px off
            H = np.array([[1, 0, 12.0], [0, 1, 0], [0, 0, 1]]) @ H
        return H, info

    monkeypatch.setattr(A, "_coarse", shifted_markers)
    al = align_views(photos["primary"], photos["secondary"], rig, AlignConfig(dense=False))
    assert al.info["method"] == "calibrated"
    assert "from the calibrated geometry" in al.info["coarse_failed"]["markers"]
    assert alignment_error(al, truth["primary"], truth["secondary"])["median_px"] < 0.01


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_default_config_meets_the_goal_at_other_capture_seeds(seed):
    """The goal holds over the photos' noise draws, not at CI's seed alone. Before the refit's information cap
    (AlignConfig.information_cap) these seeds missed it (0.54, 0.56, 0.64 px: a minority of confident matches on
    the glossy ramps, whose shading differs between the views, moved the refitted plane by ~0.5 px; at seed 4 the
    uncapped refit still does: the test sees the failure it guards against)."""
    pair = _uniform_pair(seed)
    _, err = _align(pair)
    assert err["median_px"] <= GOAL_PX / 2 and err["p90_px"] <= GOAL_PX, err
    if seed == 4:
        _, uncapped = _align(pair, information_cap=None)
        assert uncapped["median_px"] > GOAL_PX, uncapped


def test_calibrated_homography_is_exact_and_warp_follows_the_map(mini_uniform):
    """The twin's cameras are its calibration, so the plane-induced homography is exact: this checks the
    undistortion/distortion conventions and alignment_error itself against the independent sidecars."""
    rig, photos, truth = mini_uniform
    al, err = _align(mini_uniform, coarse="calibrated", dense=False)
    assert err["median_px"] < 0.01 and err["p90_px"] < 0.02, err
    # warping the secondary's sidecar into the primary's grid gives the primary's sidecar (in texels)
    warped = warp_to_primary(truth["secondary"], al)
    both = np.isfinite(warped).all(axis=2) & np.isfinite(truth["primary"]).all(axis=2)
    d = np.linalg.norm(warped[both] - truth["primary"][both], axis=1)
    assert both.sum() > 12000 and np.median(d) < 0.02
    off_view = np.isnan(al.map).any(axis=2)  # primary pixels whose plane point the secondary does not see
    assert 0 < off_view.sum() < 1000
    assert np.array_equal(np.isnan(warp_to_primary(photos["secondary"], al)).any(axis=2), off_view)


def test_markers_coarse_step_and_its_clear_failure(mini_uniform):
    al, err = _align(mini_uniform, coarse="markers", dense=False)
    assert err["median_px"] <= GOAL_PX, err
    assert len(al.info["markers"][1]) >= 2  # markers of ~20 px: only some decode in the 45 deg view
    with pytest.raises(AlignmentError, match=r"markers: \d of the frame's 8 markers found in the \w+ photo"):
        _align(mini_uniform, coarse="markers", min_markers=8)


# --- synthetic pairs with a known mapping -----------------------------------------------------------------

def _texture(x, y, seed=0):
    """A smooth random texture, evaluated exactly at any (x, y): a sum of plane waves, exponentiated (HDR)."""
    rng = np.random.default_rng(seed)
    v = np.zeros(np.shape(x))
    for _ in range(40):
        k, a, ph = rng.uniform(0.05, 0.6), rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi)
        v += np.cos(k * (np.cos(a) * x + np.sin(a) * y) + ph) / np.sqrt(40)
    return np.repeat(np.exp(0.8 * v)[..., None], 3, axis=2)


def _stub_rig(W, H):
    """Two identical distortion-free cameras looking at the plane z = 0 from 300 mm: their plane-induced
    homography is the identity, so coarse='calibrated' makes the dense step start from offset 0."""
    K = np.array([[300.0, 0, (W - 1) / 2], [0, 300.0, (H - 1) / 2], [0, 0, 1]])
    cams = {n: Camera(n, W, H, K, np.zeros(5), np.eye(3), [0, 0, 300.0]) for n in ("primary", "secondary")}
    sample = SimpleNamespace(origin=(0.0, 0.0, 0.0), x_axis=(1.0, 0.0, 0.0), y_axis=(0.0, 1.0, 0.0))
    return SimpleNamespace(name="stub", camera=lambda n: cams[n], frame=None, sample=sample)


def _grid(W, H):
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    return xx, yy


def test_sift_recovers_a_known_homography():
    W, H = 240, 180
    xx, yy = _grid(W, H)
    primary = _texture(xx, yy, seed=1).astype(np.float32)
    Ht = np.array([[0.92, 0.05, 9.0], [-0.04, 0.88, 14.0], [1.5e-4, -2e-4, 1.0]])
    secondary = cv2.warpPerspective(primary, Ht, (W, H), flags=cv2.INTER_LINEAR)  # primary point p lands at Ht p
    al = align_views(primary, secondary, _stub_rig(W, H), AlignConfig(dense=False))
    assert al.info["inliers"] >= 12
    x, y = xx[30:-30:10, 30:-30:10].ravel(), yy[30:-30:10, 30:-30:10].ravel()
    pts = np.stack([x, y, np.ones_like(x)], axis=1)
    true = pts @ Ht.T
    got = pts @ al.homography.T
    assert np.abs(got[:, :2] / got[:, 2:] - true[:, :2] / true[:, 2:]).max() < 0.25
    assert np.allclose(al.map[30, 30], true[0, :2] / true[0, 2], atol=0.25)  # map = homography (no distortion)


@pytest.mark.parametrize("shift", [(2.3, -1.6), (-1.0, 0.5)])
def test_patchmatch_recovers_an_integer_plus_subpixel_shift(shift):
    W, H = 160, 120
    xx, yy = _grid(W, H)
    s = np.array(shift)
    primary, secondary = _texture(xx, yy), _texture(xx - s[0], yy - s[1])  # primary p is seen at p + s
    al = align_views(primary, secondary, _stub_rig(W, H), AlignConfig(coarse="calibrated", refine_passes=0))
    x0, y0, x1, y1 = al.info["dense"]["roi_xyxy"]
    err = np.linalg.norm(al.map - np.stack([xx + s[0], yy + s[1]], axis=2), axis=2)[y0:y1, x0:x1]
    assert al.info["dense"]["accepted_fraction"] > 0.9
    assert np.median(err) < 0.06 and np.percentile(err, 90) < 0.15, (np.median(err), np.percentile(err, 90))


def test_dense_keeps_a_local_departure_from_the_plane():
    """A 'raised' square moved by an extra (1.2, 0.7) px: no homography explains it. The refit follows the
    rest (the plane) and the gate lets the square keep its own PatchMatch offsets. (The stub's shift is no
    height of its calibrated plane, so the refit here frees the whole homography.)"""
    W, H = 160, 120
    xx, yy = _grid(W, H)
    s = np.array([1.5, -0.5])
    bump = (np.abs(xx - 80) < 22) & (np.abs(yy - 60) < 22)
    extra = np.where(bump[..., None], [1.2, 0.7], 0.0)
    disp = s + extra
    primary = _texture(xx, yy, seed=3)
    # secondary(q) = texture(q - disp) holds where disp is constant around q (the bump's interior and outside)
    secondary = np.where(bump[..., None], _texture(xx - s[0] - 1.2, yy - s[1] - 0.7, seed=3),
                         _texture(xx - s[0], yy - s[1], seed=3))
    al = align_views(primary, secondary, _stub_rig(W, H), AlignConfig(coarse="calibrated", refit="homography"))
    err = np.linalg.norm(al.map - np.stack([xx, yy], axis=2) - disp, axis=2)
    inner = (np.abs(xx - 80) < 12) & (np.abs(yy - 60) < 12)
    x0, y0, x1, y1 = al.info["dense"]["roi_xyxy"]
    roi = np.zeros_like(bump)
    roi[y0:y1, x0:x1] = True
    outside = roi & (np.abs(xx - 80) > 34) | roi & (np.abs(yy - 60) > 34)
    assert np.median(err[inner]) < 0.15, np.median(err[inner])
    assert np.median(err[outside]) < 0.05, np.median(err[outside])


def test_deterministic_for_a_seed():
    W, H = 160, 120
    xx, yy = _grid(W, H)
    primary, secondary = _texture(xx, yy, seed=2), _texture(xx - 1.7, yy + 0.4, seed=2)
    rig = _stub_rig(W, H)
    a = align_views(primary, secondary, rig, AlignConfig(seed=5))
    b = align_views(primary, secondary, rig, AlignConfig(seed=5))
    assert np.array_equal(a.map, b.map, equal_nan=True) and np.array_equal(a.homography, b.homography)


def test_cost_volume_and_direct_costs_agree():
    g = torch.Generator().manual_seed(0)
    src, tgt = torch.rand(16, 20, 24, generator=g), torch.rand(16, 20, 24, generator=g)
    vol, direct = PatchCost(src, tgt, 5, 3, 1e9), PatchCost(src, tgt, 5, 3, 0)
    assert vol.volume is not None and direct.volume is None
    idx = torch.randint(0, vol.sentinel + 1, (4, 20, 24), generator=g)  # includes the "no candidate" sentinel
    a, b = vol(idx), direct(idx)
    assert torch.equal(torch.isinf(a), idx == vol.sentinel) and torch.equal(torch.isinf(b), idx == vol.sentinel)
    fin = torch.isfinite(a)
    assert torch.allclose(a[fin], b[fin], rtol=1e-4)
    runs = [patchmatch(c, init_noise=2, jumps=(2, 1), searches=(3, 1), iterations=4,
                       generator=torch.Generator().manual_seed(1)) for c in (vol, direct)]
    assert torch.equal(runs[0][0], runs[1][0])


def test_exhaustive_search_in_bands_is_one_volume_searched_whole():
    """`exhaustive` computes its volume in bands of rows with a halo; each band's answer must be what one
    volume over the whole image gives (argmin, its sub-pixel fit, the cost of offset 0)."""
    g = torch.Generator().manual_seed(3)
    src, tgt = torch.rand(16, 41, 30, generator=g), torch.rand(16, 41, 30, generator=g)
    whole = PatchCost(src, tgt, 5, 3, float("inf"))
    off = whole.decode(whole.volume[:-1].argmin(dim=0).reshape(whole.shape))
    step, cmin, hess, lam_min = subpixel(whole, off)
    c_zero = whole(whole.encode(torch.zeros_like(off))[None])[0]
    one_band = exhaustive(src, tgt, 5, 3, float("inf"))
    bands = exhaustive(src, tgt, 5, 3, 2 * 50 * 30 * 4 * 12)  # 12 rows a band: 2 rows kept each, 21 bands
    for got in (one_band, bands):
        assert torch.equal(got["off"], off)
        for name, want in (("step", step), ("cmin", cmin), ("hess", hess), ("c_zero", c_zero)):
            torch.testing.assert_close(got[name], want, rtol=1e-5, atol=1e-5)
        assert torch.equal(torch.isnan(got["lam_min"]), torch.isnan(lam_min))


RAISED_MM = 0.3


def _raised(a, b):
    """The raised square of the pyramid test, in sample-plane mm."""
    return (np.abs(a - 10) < 8) & (np.abs(b + 5) < 8)


def _surface(rig, name, raised_mm: float = RAISED_MM):
    """Where each pixel of `rig`'s camera `name` sees the sample: a plane with the square `_raised` lifted by
    `raised_mm` along its normal (its side walls ignored). Returns the (H, W, 3) world points and (H, W, 2)
    sample-plane coordinates (mm)."""
    cam, sp = rig.camera(name), rig.sample
    o, xa, ya = (np.asarray(v, float) for v in (sp.origin, sp.x_axis, sp.y_axis))
    normal = np.cross(xa, ya)
    xx, yy = _grid(cam.width, cam.height)
    uv = np.stack([xx.ravel(), yy.ravel()], axis=1)
    flat = cam.plane_points(uv, o, normal)
    top = cam.plane_points(uv, o + raised_mm * normal, normal)
    ab_top = (top - o) @ np.stack([xa, ya], axis=1)
    on = _raised(*ab_top.T)
    X = np.where(on[:, None], top, flat)
    ab = np.where(on[:, None], ab_top, (flat - o) @ np.stack([xa, ya], axis=1))
    return X.reshape(cam.height, cam.width, 3), ab.reshape(cam.height, cam.width, 2)


def test_two_level_pyramid_on_the_paper_rig_cameras():
    """The paper rig's two cameras (their calibrated distortion), binned 3 x 3 to 888 x 768 px to stay fast,
    aligned through the pyramid (pyramid_width 300: a 296-px binned level, then the whole +-3 px window at
    full width). The sample is flat except for a square raised 0.3 mm, which no homography of the plane
    explains: the map must follow the plane and the raised square. Truth: where the secondary camera sees
    each primary pixel's surface point (projected, not aligned)."""
    paper = twin.load_rig("paper")
    cams = {n: paper.camera(n).resized(1 / 3) for n in ("primary", "secondary")}
    rig = SimpleNamespace(name="paper/3", camera=cams.__getitem__, frame=paper.frame, sample=paper.sample)
    photos = [_texture(*(4 * _surface(rig, n)[1]).transpose(2, 0, 1), seed=4).astype(np.float32)
              for n in ("primary", "secondary")]  # 4 rad/mm: features of ~0.3-3 mm
    al = align_views(*photos, rig, AlignConfig(pyramid_width=300))
    assert al.info["pyramid_factor"] == 3 and al.info["dense"]["search"] == "exhaustive"
    assert al.info["dense"]["binned"]["search"] == "patchmatch"
    X, ab = _surface(rig, "primary")
    want = cams["secondary"].project(X.reshape(-1, 3))[0].reshape(X.shape[:2] + (2,))
    x0, y0, x1, y1 = al.info["dense"]["roi_xyxy"]
    err = np.linalg.norm(al.map - want, axis=2)[y0:y1, x0:x1]
    a, b = ab[y0:y1, x0:x1, 0] - 10, ab[y0:y1, x0:x1, 1] + 5
    inner, outside = (np.abs(a) < 6) & (np.abs(b) < 6), (np.abs(a) > 10) | (np.abs(b) > 10)
    assert np.median(err[outside]) < GOAL_PX / 10 and np.percentile(err[outside], 90) < GOAL_PX / 5, \
        (np.median(err[outside]), np.percentile(err[outside], 90))
    assert np.median(err[inner]) < GOAL_PX / 2, np.median(err[inner])
    plane = align_views(*photos, rig, AlignConfig(coarse="calibrated", dense=False))  # the exact plane's map
    assert np.median(np.linalg.norm(plane.map - want, axis=2)[y0:y1, x0:x1][inner]) > GOAL_PX  # a real departure


def test_bad_input_is_refused_clearly(mini_uniform):
    rig, photos, truth = mini_uniform
    p, s = photos["primary"], photos["secondary"]
    bad = p.copy()
    bad[5, 7, 1] = np.nan
    with pytest.raises(ValueError, match="primary image has 1 pixels with NaN"):
        align_views(bad, s, rig)
    with pytest.raises(ValueError, match=r"secondary image is 111x96 \(W x H\) but camera 'secondary' is 222x192"):
        align_views(p, s[::2, ::2], rig)
    with pytest.raises(ValueError, match=r"must be \(H, W\) or \(H, W, 3\)"):
        align_views(p, np.zeros((192, 222, 4), np.float32), rig)
    flat = np.ones_like(p)
    with pytest.raises(ValueError, match="sift: too few keypoints"):
        align_views(flat, flat, rig, AlignConfig(coarse="sift"))
    auto = align_views(flat, flat, rig, AlignConfig(dense=False))  # "auto" falls back, saying why
    assert auto.info["method"] == "calibrated" and set(auto.info["coarse_failed"]) == {"sift", "markers"}
    xx, yy = _grid(160, 120)  # two unrelated textures: keypoints, but no matches that pass the ratio test
    with pytest.raises(ValueError, match=r"sift: only \d+ matches pass the ratio test 0.5 \(need >= 12\)"):
        align_views(_texture(xx, yy, seed=1), _texture(xx, yy, seed=7), _stub_rig(160, 120), AlignConfig(coarse="sift"))
    al, _ = _align(mini_uniform, coarse="calibrated", dense=False)
    with pytest.raises(ValueError, match="pixel_texel_primary must be"):
        alignment_error(al, truth["primary"][:, :100], truth["secondary"])
    with pytest.raises(ValueError, match="coarse must be one of"):
        AlignConfig(coarse="artag")
    with pytest.raises(ValueError, match="patch must be a positive odd"):
        AlignConfig(patch=6)
    with pytest.raises(ValueError, match=r"information_cap must be a percentile in \(0, 100\] or None"):
        AlignConfig(information_cap=0)

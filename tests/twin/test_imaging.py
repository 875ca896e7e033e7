"""Camera image formation against independent oracles: Mitsuba 3 for the radiometry (a Lambertian
plate under one LED, seen by the primary camera), OpenCV for the geometry (ArUco detection of the
rendered holder-frame markers, projection of texel centres)."""
from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

import twin
from twin.camera.imaging import (KIND_MARKER, KIND_SAMPLE, pattern_groups, render, render_reference, trace_pixels,
                                 trace_pixels_numpy)


def uniform_maps(size=120.0, R=32, rho_d=0.5, rho_s=0.0, alpha=0.2, beta=0.0):
    """A homogeneous sample, built directly (twin.materials.samples validates the same fields)."""
    f = np.float32
    return SimpleNamespace(rho_d=np.full((R, R, 3), rho_d, f), rho_s=np.full((R, R, 3), rho_s, f),
                           alpha=np.full((R, R, 2), alpha, f), normal=np.tile(np.array([0, 0, 1], f), (R, R, 1)),
                           tangent=np.tile(np.array([1, 0, 0], f), (R, R, 1)), transparency=np.full((R, R), beta, f),
                           size_mm=size)


@pytest.fixture(scope="module")
def mini():
    return twin.load_rig("mini")


def test_mitsuba_lambertian_plate_under_one_led(mini):
    """Twin vs Mitsuba 3 (scalar_rgb, `direct` integrator, point light): a 120 mm Lambertian plate
    (rho 0.5) lit by one upper LED with an isotropic profile (cos^0, i.e. a point light), seen by the
    primary camera with the same K (no distortion, principal point at the image centre, as Mitsuba's
    perspective camera) and pose. Mean relative difference <= 1% (the goal): Mitsuba's box
    filter averages each pixel over 64 samples (Monte-Carlo noise ~0.1% on this smooth image), the twin
    takes the pixel centre (supersample 1)."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    cam = mini.camera("primary")
    W, H = cam.width, cam.height
    f = cam.K[0, 0]
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    cam = replace(cam, K=K, dist=np.zeros(5))
    prof = np.zeros_like(mini.leds.profile)  # p = 0: isotropic point emitter
    rig = replace(mini, cameras={"primary": cam}, frame=None, leds=replace(mini.leds, profile=prof))
    led = int(np.argmax(np.where(rig.is_bottom, -np.inf, rig.led_positions[:, 2])))  # a top-board LED
    surfaces = trace_pixels(rig, "primary", uniform_maps(), supersample=1)
    w = np.zeros((1, rig.num_leds, 3), np.float32)
    w[0, led] = 1.0
    ours = render(rig, "primary", surfaces, w)[0, ..., 0]

    T = mi.ScalarTransform4f
    C = cam.centre
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov_axis": "x", "fov": float(np.degrees(2 * np.arctan(W / 2 / f))),
                   "to_world": T().look_at(origin=[float(v) for v in C], target=[float(v) for v in C + cam.R[2]],
                                           up=[float(v) for v in -cam.R[1]]),
                   "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 64}},
        "plate": {"type": "rectangle", "to_world": T().translate([0.0, 0.0, -122.0]) @ T().scale([60.0, 60.0, 1.0]),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}},
        # the twin's physical convention has r in metres and the scene is in mm: I / r_m^2 = 1e6 I / r_mm^2
        "light": {"type": "point", "position": [float(v) for v in rig.led_positions[led]],
                  "intensity": {"type": "rgb", "value": [float(rig.leds.intensity[led, 0]) * 1e6] * 3}},
    })
    theirs = np.asarray(mi.render(scene, seed=1))[..., 0]
    kind = surfaces.host().kind.reshape(H, W)
    inner = (kind == KIND_SAMPLE)
    inner[1:-1, 1:-1] &= inner[:-2, 1:-1] & inner[2:, 1:-1] & inner[1:-1, :-2] & inner[1:-1, 2:]  # off the edges
    inner[[0, -1], :] = False
    inner[:, [0, -1]] = False
    assert inner.sum() > 10000
    rel = np.abs(ours[inner] - theirs[inner]) / theirs[inner]
    assert rel.mean() <= 0.01, rel.mean()
    assert np.median(rel) <= 0.005


@pytest.mark.slow
def test_rendered_markers_detected_where_projected(mini):
    """OpenCV's ArUco detector finds every holder-frame marker in view in a uniformly lit render, at the
    corners that Camera.project gives for the rig's marker geometry (mean <= 0.5 px, max <= 1.5 px). Rendered at twice the mini
    rig's resolution (the 45 deg view foreshortens a 6x6 marker to ~2.6 px per cell at 1/12 resolution,
    below what the detector resolves), lit by the top boards only to keep it fast."""
    import cv2

    top = np.isin(mini.leds.board, [1, 2])
    rig = replace(mini, leds=mini.leds.subset(top), cameras={n: c.resized(2) for n, c in mini.cameras.items()})
    for cam_name in ("primary", "secondary"):
        cam = rig.camera(cam_name)
        surfaces = trace_pixels(rig, cam_name, uniform_maps(), supersample=2)  # anti-aliased marker edges
        img = render(rig, cam_name, surfaces, np.ones((1, rig.num_leds)))[0].mean(-1)
        g = np.clip(img / np.percentile(img, 99) * 255, 0, 255).astype(np.uint8)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250), params)
        corners, ids, _ = det.detectMarkers(g)
        in_view = [i for i, c in zip(rig.frame.marker_ids, rig.frame.marker_corners)
                   if np.all((cam.project(c)[0] > 3) & (cam.project(c)[0] < [cam.width - 4, cam.height - 4]))]
        assert len(in_view) >= 5, cam_name  # the primary's field cuts the -x side markers at the image edge
        assert ids is not None and set(in_view) <= set(ids.ravel().tolist()), (cam_name, ids, in_view)
        errors = []
        for c, i in zip(corners, ids.ravel()):
            if i not in in_view:
                continue
            uv, _ = cam.project(rig.frame.marker_corners[i])
            # the detector's corner order follows the marker image; compare as sets of points
            errors.append(np.linalg.norm(c[0][:, None] - uv[None], axis=-1).min(axis=1))
        errors = np.concatenate(errors)
        # Sub-pixel corner refinement on a 2x2-supersampled render: typically 0.1-0.4 px, up to ~1 px on
        # the 45 deg view's foreshortened corners. A geometric error (K, pose, axis swap, marker layout)
        # shows as several pixels or as wrong / missing ids.
        assert errors.mean() <= 0.5 and errors.max() <= 1.5, (cam_name, errors)


def test_pixel_texel_ground_truth_matches_projection(mini):
    """The sidecar's per-pixel texel coordinate, projected back through the camera, lands on the pixel:
    texel centre (i, j) is at world (-s/2 + (j + 0.5) s/W, -s/2 + (i + 0.5) s/H, z0)."""
    maps = uniform_maps(R=64)
    for cam_name in ("primary", "secondary"):
        s = trace_pixels(mini, cam_name, maps, supersample=1)
        tex = s.pixel_texel()
        v, u = np.nonzero(~np.isnan(tex[..., 0]))
        rc = tex[v, u]
        step = maps.size_mm / 64
        xyz = np.stack([-60 + (rc[:, 1] + 0.5) * step, -60 + (rc[:, 0] + 0.5) * step, np.full(len(rc), -122.0)], 1)
        uv, _ = mini.camera(cam_name).project(xyz)
        assert np.abs(uv - np.stack([u, v], 1)).max() < 1e-6


def test_frame_shadows_and_bottom_light(mini):
    """Physics visible in the images: bottom LEDs light the acrylic board and a transparent sample but not
    the opaque frame; with a low +x-wall LED the frame shades a strip of board just inside its -x... edge."""
    s = trace_pixels(mini, "primary", uniform_maps(beta=0.25), supersample=1)
    w = np.zeros((1, mini.num_leds, 3), np.float32)
    w[0, mini.is_bottom] = 1.0
    img = render(mini, "primary", s, w)[0, ..., 1].ravel()
    kind = s.host().kind
    assert np.all(img[kind == KIND_MARKER] == 0)
    sample, board = img[kind == KIND_SAMPLE], img[kind == 4]
    assert sample.min() > 0 and np.median(sample) < 0.5 * np.median(board)  # beta 0.25 vs the board's 1


# --- the device kernels against their numpy / float32 twins (the oracles) --------------------------------
@pytest.fixture(scope="module")
def ramps():
    from twin.materials.samples import load_sample

    return load_sample("ramps", resolution=128)  # S = 2 sub-pixel rays on the mini rig


@pytest.mark.parametrize("cam_name", ["primary", "secondary"])
@pytest.mark.parametrize("textured", [True, False])
def test_trace_kernel_is_the_numpy_trace(mini, ramps, cam_name, textured):
    """trace_kernel (float64, no contraction) against the numpy trace: the same hit everywhere, the float32
    forward inputs within 1 ulp of the numpy values rounded to float32 (measured: identical), the texel
    coordinates to 1e-12; a crop of rows traces the same rays."""
    maps = ramps if textured else None
    ours = trace_pixels(mini, cam_name, maps).host()
    ref = trace_pixels_numpy(mini, cam_name, maps)
    assert ours.supersample == ref.supersample and ours.supersample == (2 if textured else 1)
    np.testing.assert_array_equal(ours.kind, ref.kind)
    for f in ("position", "normal", "tangent", "rho_d", "rho_s", "alpha_x", "alpha_y", "transparency"):
        np.testing.assert_array_max_ulp(getattr(ours, f), getattr(ref, f).astype(np.float32), maxulp=1)
    np.testing.assert_array_equal(np.isnan(ours.texel), np.isnan(ref.texel))
    on = ~np.isnan(ref.texel)
    np.testing.assert_allclose(ours.texel[on], ref.texel[on], rtol=1e-12, atol=1e-12)
    crop = trace_pixels(mini, cam_name, maps, rows=(40, 47)).host()
    n = crop.kind.size
    start = 40 * mini.camera(cam_name).width * ours.supersample ** 2
    for f in PixelSurfacesFields:
        np.testing.assert_array_equal(getattr(crop, f), getattr(ours, f)[start:start + n])


PixelSurfacesFields = ("position", "normal", "tangent", "rho_d", "rho_s", "alpha_x", "alpha_y", "transparency", "kind",
                       "texel")


def test_render_is_the_float32_forward_model(mini, ramps):
    """The capture's render (contraction-free lumitexels, float64 projection, device finishing) against the
    public forward model's fused float32 kernel with numpy finishing, on the plan's kinds of pattern (a signed
    learned pair, a line, uniform, bottom, an all-dark one): every value within 1e-5 relative + 1e-6 of the
    image's largest (float32 sums in another order)."""
    from twin.capture.plan import build_patterns

    pats = build_patterns(mini)
    w = np.concatenate([pats.weights[[0, 1, 70, 129, 128]], np.zeros((1, mini.num_leds, 3))])
    for cam_name in ("primary", "secondary"):
        s = trace_pixels(mini, cam_name, ramps, rows=(60, 76))
        ours = render(mini, cam_name, s, w)
        ref = render_reference(mini, cam_name, s, w)
        assert ours.shape == ref.shape == (6, 16, mini.camera(cam_name).width, 3)
        assert np.all(ours[-1] == 0) and ref[:5].min() >= 0
        for k in range(5):
            tol = 1e-5 * np.abs(ref[k]) + 1e-6 * np.abs(ref[k]).max()
            assert np.all(np.abs(ours[k] - ref[k]) <= tol), (cam_name, k)


def test_render_applies_the_rigs_per_pixel_flat_field(mini, ramps):
    """A rig's per-pixel falloff map (Rig.flat_fields, from a flat-field calibration or the twin's true device)
    multiplies the rendered radiance pixel by pixel, in the capture's render and in its reference alike."""
    from twin.capture.plan import build_patterns

    w = build_patterns(mini).weights[[129]]  # uniform light
    cam = mini.camera("primary")
    m = np.linspace(0.6, 1.0, cam.height * cam.width, dtype=np.float32).reshape(cam.height, cam.width)
    dusty = replace(mini, flat_fields={"primary": m})
    s = trace_pixels(mini, "primary", ramps, rows=(60, 68))
    plain, ours, ref = render(mini, "primary", s, w), render(dusty, "primary", s, w), render_reference(dusty, "primary", s, w)
    lit = plain > 1e-3 * plain.max()
    want = plain * m[60:68][None, :, :, None]
    assert lit.sum() > 1000
    assert np.allclose(ours[lit], want[lit], rtol=1e-6) and np.allclose(ref[lit], want[lit], rtol=2e-5)
    assert dusty.digest() != mini.digest()


def test_pattern_groups_render_only_lit_leds(mini):
    """Patterns are grouped by the LED classes they light; each group evaluates only its lit LEDs."""
    from twin.capture.plan import build_patterns

    pats = build_patterns(mini)
    groups = pattern_groups(pats.weights, mini.is_bottom)
    bottom = [g for g in groups if np.array_equal(g[0], [pats.names.index("bottom")])]
    assert len(bottom) == 1 and np.array_equal(bottom[0][1], np.flatnonzero(mini.is_bottom))
    upper = [g for g in groups if g is not bottom[0]]
    assert all(not mini.is_bottom[leds].any() for _, leds in upper)
    assert sorted(np.concatenate([ks for ks, _ in groups]).tolist()) == list(range(len(pats.names)))

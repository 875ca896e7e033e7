"""Self-checks of the twin that `hemicube validate` runs before its end-to-end run: the rig model (folder round
trip, cross layout, camera projection against OpenCV, the paper rig against the released layout) and the
forward model (the authors' renderer, a Lambertian closed form, fused against materialised). Each says what
it compared, its worst error and its threshold."""
from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class Check:
    name: str
    compared: str
    worst: float
    threshold: float
    unit: str

    @property
    def passed(self) -> bool:
        return bool(np.isfinite(self.worst) and self.worst <= self.threshold)


def reference_dir() -> Path | None:
    """The released OpenSVBRDF configuration: $HEMICUBE_REFERENCE, else ../shared/reference beside the repo."""
    env = os.environ.get("HEMICUBE_REFERENCE")
    cand = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "reference" / "opensvbrdf_lightstage"
    return cand if (cand / "lights.bin").is_file() else None


def rig_checks(rig) -> list[Check]:
    import cv2

    from twin.rig.format import load_rig_dir, save_rig

    checks = []
    with tempfile.TemporaryDirectory() as d:
        back = load_rig_dir(save_rig(rig, Path(d) / "rig"))
    same = back.digest() == rig.digest() and all(
        np.array_equal(getattr(back.leds, k), getattr(rig.leds, k)) for k in rig.leds.ARRAYS)
    checks.append(Check("rig folder round trip", f"{rig.num_leds} LEDs, {len(rig.cameras)} cameras saved and "
                        "reloaded, arrays and digest", 0.0 if same else 1.0, 0.0, "mismatches"))
    cp = rig.leds.cross_pixel.astype(np.int64)
    dup = rig.num_leds - len(np.unique(cp[:, 1] * 1000 + cp[:, 0]))
    checks.append(Check("cross layout bijection", "LED index <-> cross-image pixel", float(dup), 0.0,
                        "collisions"))
    pts = np.random.default_rng(0).uniform(-75, 75, (200, 3)) * [1, 1, 0] + rig.sample.origin
    worst = 0.0
    for cam in rig.cameras.values():
        uv, _ = cam.project(pts)
        ref, _ = cv2.projectPoints(pts, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist)
        worst = max(worst, float(np.abs(uv - ref.reshape(-1, 2)).max()))
    # Threshold: OpenCV receives R as a rotation vector, i.e. the nearest exact rotation; a calibration file
    # that stores R in float32 (the released one) is orthonormal to ~1e-7, which moves a point by
    # <= f * 1e-7 ~ 5e-4 px at f = 4923 px. Any real modelling error is orders of magnitude larger.
    checks.append(Check("camera projection vs OpenCV", "200 sample-plane points, every camera, "
                        "cv2.projectPoints", worst, 1e-3, "px"))
    return checks


def reference_checks(ref: Path) -> list[Check]:
    import twin
    from twin.rig.opensvbrdf_import import import_opensvbrdf

    released = import_opensvbrdf(ref)
    paper = twin.load_rig("paper")
    up = ~paper.is_bottom
    dist = np.linalg.norm(paper.led_positions[up] - released.led_positions, axis=1).max()
    return [Check("paper rig vs released layout", "12,288 upper LED positions vs lights.bin", float(dist), 1.0, "mm")]


def forward_checks(rig, device: str, ref: Path | None) -> list[Check]:
    import twin
    from twin.bench import random_points

    checks = []
    if ref is not None:
        from twin.rig.opensvbrdf_import import import_opensvbrdf

        released = import_opensvbrdf(ref)
        # Reference §2.7 case C (anisotropic GGX): sum, max and argmax of the authors' renderer
        m = twin.lumitexels(released, [[0, 0, -122.0]], [[0, 0, 1.0]], [[1.0, 0, 0]], [[0.0] * 3], [[1.0] * 3],
                            [0.05], [0.3], convention="opensvbrdf", device=device)[0, :, 0].astype(np.float64)
        rel = max(abs(m.sum() / 0.100491 - 1), abs(m.max() / 4.99217e-4 - 1), float(np.argmax(m) != 4959))
        checks.append(Check("lumitexel vs authors' renderer", "reference §2.7 case C (sum, max, argmax), "
                            "OpenSVBRDF convention", rel, 1e-5, "relative"))
    # Closed form: a Lambertian plate under every upper LED (physical convention, centre of the sample)
    x = np.array([rig.sample.origin])
    m = twin.lumitexels(rig, x, [rig.sample.normal], [rig.sample.x_axis], [[1.0] * 3], [[0.0] * 3], [0.3], [0.3],
                        device=device)[0, :, 0]
    d = rig.led_positions - x
    r = np.linalg.norm(d, axis=1)
    wi = d / r[:, None]
    want = np.where(~rig.is_bottom, rig.leds.intensity[:, 0] / np.pi * np.clip(wi @ np.asarray(rig.sample.normal), 0,
                    None) * np.clip(-(wi * rig.led_normals).sum(1), 0, None) / (r * 1e-3) ** 2, 0.0)
    if rig.led_profile == "cosine" and np.all(rig.leds.profile[:, 0] == 1):
        checks.append(Check("Lambertian plate vs closed form", f"{rig.num_leds} LEDs, cos.cos/r^2 in float64",
                            float(np.abs(m - want).max() / np.abs(want).max()), 1e-5, "relative"))
    pts = random_points(64)
    w = np.random.default_rng(1).uniform(0, 1, (16, rig.num_leds, 3))
    lum = twin.lumitexels(rig, **pts, device=device).astype(np.float64)
    fused = twin.measurements(rig, **pts, patterns=w, device=device)
    want = np.einsum("klc,plc->pkc", w, lum)
    checks.append(Check("fused measurements vs lumitexels", "64 random points x 16 patterns, fused kernel vs "
                        "float64 projection of the lumitexels", float(np.abs(fused - want).max() / np.abs(want).max()),
                        1e-5, "relative"))
    return checks

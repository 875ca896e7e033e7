"""The refit's photos read at each colour's nearest photosite (issue #14, nineteenth session): is the demosaic what
mixes the ink's light into the stock next to it (d1)?

    python docs/bench/nearest_site_refit_2026-11-28.py validate --sample paper -o OUT

runs `hemicube` with the refit's extraction (`extract(..., demosaic="malvar2004")`, pipeline step 12) replaced: each
texel's R, G and B are the values of the nearest photosite of that colour to its centre in the capture's mosaic (the
HDR merge's bilinear demosaic keeps each photosite's own colour), flat-fielded there, then the colour matrix: no
interpolation across the texel's edge but the photosite's own 1 px. A diagnostic, not a method: compare with
`hemicube validate --sample paper -o OUT2` by `python docs/bench/edge_misfit_2026-11-28.py analyse OUT2 OUT`.
"""
import sys
import threading

import numpy as np

import reconstruction.extraction as E
from twin.camera.bayer import cfa_index

orig_extract, orig_corrected, orig_sample = E.extract, E.corrected, E._sample
tl = threading.local()


def corrected_flat(img, camera, calibration=None):
    flat, C = calibration if calibration is not None else E.calibration_of(camera)
    tl.C, tl.bayer, tl.pending = C, camera.sensor.bayer, True
    return img * flat


def sample_sites(img, taps, footprint="point", ksize=0):
    from twin.camera.correction import apply_colour_matrix

    if not getattr(tl, "pending", False):
        return orig_sample(img, taps, footprint, ksize)
    tl.pending = False
    (i00, _, _, _), fx, fy, inside, (H, W) = taps
    x, y = (i00 % W) + fx[:, 0], (i00 // W) + fy[:, 0]
    cfa = cfa_index(tl.bayer, H, W)
    out = np.zeros((len(x), 3))
    bx, by = np.floor(x).astype(int), np.floor(y).astype(int)
    best = np.full((len(x), 3), np.inf)
    for dy in range(-1, 3):
        for dx in range(-1, 3):
            px, py = np.clip(bx + dx, 0, W - 1), np.clip(by + dy, 0, H - 1)
            d2 = (px - x) ** 2 + (py - y) ** 2
            c = cfa[py, px]
            for ch in range(3):
                take = (c == ch) & (d2 < best[:, ch])
                best[take, ch] = d2[take]
                out[take, ch] = img[py[take], px[take], ch]
    out = np.maximum(apply_colour_matrix(out[:, None, :], tl.C)[:, 0], 0.0)
    out[~inside] = np.nan
    return out.astype(np.float32)


def extract(*a, demosaic="bilinear", **k):
    if demosaic == "bilinear":
        return orig_extract(*a, demosaic=demosaic, **k)
    E.corrected, E._sample = corrected_flat, sample_sites
    try:
        return orig_extract(*a, demosaic="bilinear", **k)
    finally:
        E.corrected, E._sample = orig_corrected, orig_sample

if __name__ == "__main__":
    from hemicube.cli import main

    E.extract = extract
    sys.exit(main(sys.argv[1:]))

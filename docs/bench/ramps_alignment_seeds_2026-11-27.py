"""Issue #14 (docs/accuracy.md, "Open", sixteenth session): the main job's two-view alignment (`ramps`, mini rig)
over capture seeds, from each coarse start, against the twin's ground truth.

    hemicube capture --rig mini --sample ramps --seed N -o DIR      # for each seed N
    python docs/bench/ramps_alignment_seeds_2026-11-27.py DIR [DIR ...]

Per capture: the alignment error (median / p90 px, primary pixels off the sample) of the pipeline's alignment
(AlignConfig(): coarse "auto", which is SIFT when it finds its matches; the refit's information capped, step 13) and,
without the cap (information_cap=None, as before step 13), of the same from each coarse start (auto, the markers', the
calibrated homography), with each refit's median shift; the calibrated homography alone (the plane at height 0, no
dense step); and, started from the calibrated homography without the cap, the first dense pass's matches on the
sample: their weighted mean offset in y (the weights the refit gives them). A record of how the numbers were
measured, not part of the pipeline.
"""
import sys
from dataclasses import replace

import numpy as np

import reconstruction.alignment as A
import twin
from twin.capture.session import CaptureSession

rig = twin.load_rig("mini")
fields = []
_refit = A._refit


def spy(H, field, roi, box, *args, **kwargs):  # the dense matches the refit is given
    fields.append((field, roi, box))
    return _refit(H, field, roi, box, *args, **kwargs)


A._refit = spy
for cap in sys.argv[1:]:
    s = CaptureSession.open(cap)
    photos = s.photo(129, 0), s.photo(129, 1)  # the uniform-light pair
    truth = s.pixel_texel(0), s.pixel_texel(1)
    for start, cap_pct in (("auto", A.AlignConfig().information_cap), ("auto", None), ("markers", None),
                           ("calibrated", None)):
        fields.clear()
        al = A.align_views(*photos, rig, config=replace(A.AlignConfig(), coarse=start, information_cap=cap_pct))
        e = A.alignment_error(al, *truth)
        print(f"{cap}: start {start} ({al.info.get('method')}), information cap {cap_pct}: median {e['median_px']:.3f} "
              f"px, p90 {e['p90_px']:.3f}, off sample {e['off_sample']}, refit shifts "
              f"{[round(r['median_shift_px'], 3) for r in al.info['dense']['refit']]}", flush=True)
        if start == "calibrated":
            field, roi, box = fields[0]
            lam, vec = np.linalg.eigh(np.nan_to_num(field["hess"]))
            cs = np.maximum(field["cmin"], 0)
            use = roi & field["known"] & np.isfinite(field["lam_min"]) & (lam[..., 1] > A.AlignConfig().gate * cs) \
                & (lam[..., 1] > 0)
            on = np.isfinite(truth[0][..., 0])[box[1]:box[3], box[0]:box[2]] & use
            w = lam[..., 1][on] / np.maximum(cs[on], 1e-3 * np.median(cs[on]) + 1e-12)
            fy = field["flow"][..., 1][on]
            print(f"    first pass from the calibrated homography: {on.sum()} sample pixels, weighted mean offset "
                  f"y {np.average(fy, weights=w):+.3f} px (median {np.median(fy):+.3f})", flush=True)
    al = A.align_views(*photos, rig, config=replace(A.AlignConfig(), coarse="calibrated", dense=False))
    print(f"    the calibrated homography alone: median {A.alignment_error(al, *truth)['median_px']:.3f} px", flush=True)

"""Issue #14's footprint experiments (docs/accuracy.md, "a narrower footprint halves paper's error"), as run.

    python docs/bench/footprint_experiments_2026-11-25.py SAMPLE OUT MODE

runs `hemicube validate`'s end-to-end function (mini rig, capture seed 1, CPU) on SAMPLE in one process with the
stages MODE names replaced, and prints the goal rows as JSON. MODE holds any of:
    mhc    the HDR merge's demosaic replaced by Malvar-He-Cutler 2004 (twin.camera.bayer.malvar2004 since the
           fifteenth session; the script's own copy of the kernels, which it replaced, agreed with it to 4e-16)
    x4     every exposure of the bracket taken 4 times (the merge averages them; since 2026-11-27 the capture's
           default is four, so x4 now makes 16)
    cell   each texel's photos the mean of 3 x 3 samples at +-1/3 texel
    raw    the primary view's photos the mean of each colour's own photosites inside the texel's cell (with
           RAW_VIEWS=both, the secondary view's too)
    hyb    each photo's bilinear value replaced by the Malvar-He-Cutler one where they differ by more than 3
           robust standard deviations; with "loc", the difference divided by the square root of the signal first
    var    the same test against the exact variance of the difference, from the HDR merge of the stored raw frames
    fp     fit, predict the photos through each view's bilinear footprint from the texel cells around each texel,
           fit again to the photos less the predicted spill (FP_ITERS times)
A record of how the numbers were measured, not part of the pipeline.
"""
import os, sys, json, time
from pathlib import Path
import numpy as np

def pixel_cells(rig, grid, cam):
    """(H, W) row and column of the texel cell each pixel's ray meets on the sample plane (unclipped, float)."""
    H, W = cam.height, cam.width
    ys, xs = np.mgrid[0:H, 0:W]
    p = cam.plane_points(np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64), rig.sample.origin,
                         rig.sample.normal) - np.asarray(rig.sample.origin)
    u, v = p @ np.asarray(rig.sample.x_axis), p @ np.asarray(rig.sample.y_axis)
    i = np.floor((v + grid.size_mm / 2) / grid.texel_mm).reshape(H, W)
    j = np.floor((u + grid.size_mm / 2) / grid.texel_mm).reshape(H, W)
    return i, j


def patch():
    import warp as wp
    import twin.camera.hdr as hdr
    from twin.camera.bayer import malvar2004
    orig = hdr.merge_hdr_device
    def merged(raws, exposures_s, sensor, gain_db=0.0, margin=hdr.DEFAULT_MARGIN):
        out = orig(raws, exposures_s, sensor, gain_db, margin)
        mos = out["mosaic"].numpy()
        rgb = malvar2004(mos, sensor.bayer).astype(np.float32)
        out["radiance"] = wp.array(rgb, dtype=wp.vec3f, device=raws.device)
        return out
    hdr.merge_hdr_device = merged

if __name__ == "__main__":
    sample, outdir, mode = sys.argv[1], Path(sys.argv[2]), sys.argv[3]
    import torch; torch.set_num_threads(1)
    if "mhc" in mode:
        patch()
    frames = None  # the capture's default (four since 2026-11-27)
    if "x4" in mode:  # four times the default
        from twin.capture.plan import DEFAULT_FRAMES
        frames = 4 * DEFAULT_FRAMES
    if "cell" in mode:
        import dataclasses
        import reconstruction.extraction as ex
        orig_extract = ex.extract
        class Shifted(ex.TextureGrid):
            def positions(self, rig):
                p = super().positions(rig)
                return p + self.texel_mm * (self._du * np.asarray(rig.sample.x_axis) + self._dv * np.asarray(rig.sample.y_axis))
        def extract(session, rig, grid, alignment, **kw):
            base = orig_extract(session, rig, grid, alignment, **kw)
            acc_l, acc_p = [], []
            for du in (-1/3, 0, 1/3):
                for dv in (-1/3, 0, 1/3):
                    g = Shifted(grid.resolution, grid.size_mm)
                    object.__setattr__(g, "_du", du); object.__setattr__(g, "_dv", dv)
                    m = orig_extract(session, rig, g, alignment, **kw)
                    acc_l.append(m.lines); acc_p.append(m.learned_photos)
            return dataclasses.replace(base, lines=np.mean(acc_l, 0).astype(np.float32),
                                       learned_photos=np.mean(acc_p, 0).astype(np.float32))
        ex.extract = extract
    if "raw" in mode:
        import dataclasses
        import reconstruction.extraction as ex
        from twin.camera.bayer import cfa_index
        from twin.camera.correction import apply_colour_matrix
        from reconstruction.data import LUMITEXEL_SCALE
        orig_extract2 = ex.extract
        def cell_reader(rig, grid, cam):
            H, W = cam.height, cam.width
            R = grid.resolution
            i, j = (a.ravel() for a in pixel_cells(rig, grid, cam))
            inside = (i >= 0) & (i < R) & (j >= 0) & (j < R) & np.isfinite(i) & np.isfinite(j)
            texel = np.where(inside, i * R + j, -1).astype(np.int64)
            ch = cfa_index(cam.sensor.bayer, H, W).ravel()
            flat, C = ex.calibration_of(cam, rig.flat_fields.get(cam.name))
            flat = flat[..., 0].ravel()
            sel = [(texel >= 0) & (ch == c) for c in range(3)]
            counts = [np.bincount(texel[s], minlength=R * R) for s in sel]
            print("photosites per texel min", cam.name, [int(c.min()) for c in counts], file=sys.stderr)
            def cellvals(img):
                img = img.reshape(-1, 3)
                out = np.stack([np.bincount(texel[sel[c]], weights=(img[sel[c], c] * flat[sel[c]]), minlength=R * R) / np.maximum(counts[c], 1) for c in range(3)], 1)
                return np.maximum(apply_colour_matrix(out, C), 0) * np.float32(LUMITEXEL_SCALE)
            return cellvals
        def extract(session, rig, grid, alignment, **kw):
            # RAW_VIEWS=both: the secondary view's learned-pattern photos read the same way (its own photosites
            # inside the same cells on the sample plane), so that both views measure the same footprint
            base = orig_extract2(session, rig, grid, alignment, **kw)
            names = list(rig.cameras)
            cellvals = cell_reader(rig, grid, rig.camera(names[0]))
            ix = ex.plan_indices(session)
            lines = np.stack([cellvals(session.photo(k, 0)) for k in ix.lines], 1).astype(np.float32)
            lp = base.learned_photos.copy()
            for k in ix.learned:
                lp[:, 0, k] = cellvals(session.photo(k, 0))
            if os.environ.get("RAW_VIEWS") == "both":
                cellvals1 = cell_reader(rig, grid, rig.camera(names[1]))
                for k in ix.learned:
                    lp[:, 1, k] = cellvals1(session.photo(k, 1))
            return dataclasses.replace(base, lines=lines, learned_photos=lp)
        ex.extract = extract
    if "fp" in mode:
        # the footprint in the fit, one outer iteration: fit; predict each texel's photos at its centre (P) and
        # through the bilinear demosaic + lookup footprint of the texel cells around it (Y = sum_j W_ij P_j, with
        # W from indicator images of the texel cells pushed through mosaic, demosaic and lookup); refit to
        # the photos less the predicted spill (Y - P)
        import reconstruction.extraction as ex
        import reconstruction.fitting as fitting
        from reconstruction.alignment import bilinear
        from reconstruction.data import LUMITEXEL_SCALE
        from twin.camera.bayer import cfa_index, demosaic
        import twin as _tw
        stash = {}
        orig_extract4 = ex.extract
        def extract(session, rig, grid, alignment, **kw):
            m = orig_extract4(session, rig, grid, alignment, **kw)
            stash["meas"], stash["grid"] = m, grid
            return m
        ex.extract = extract
        def footprint(rig, grid, cam, uv):
            """Per colour c, (3, 3, N): the weight of each texel's neighbour (dr, ds) in its photo from camera `cam`."""
            R = grid.resolution
            ii, jj = (np.clip(a, 0, R - 1).astype(int) for a in pixel_cells(rig, grid, cam))
            ch = cfa_index(cam.sensor.bayer, cam.height, cam.width)
            r = np.arange(R * R) // R; s_ = np.arange(R * R) % R
            out = []
            for c in range(3):
                Wc = np.zeros((3, 3, R * R))
                for a in range(3):
                    for b in range(3):
                        ind = ((ii % 3 == a) & (jj % 3 == b) & (ch == c)).astype(np.float64)
                        resp = demosaic(ind, cam.sensor.bayer)[..., c]
                        val = bilinear(resp[..., None], uv[:, 0], uv[:, 1])[:, 0]
                        dr = (a - r) % 3; dr = np.where(dr == 2, -1, dr)
                        ds = (b - s_) % 3; ds = np.where(ds == 2, -1, ds)
                        Wc[dr + 1, ds + 1, np.arange(R * R)] = val
                out.append(Wc)
            return out
        def through(Wcs, P, R):
            """Y (N, K, 3) = sum over the 3x3 neighbours of W * P (edge texels clamp)."""
            Pg = P.reshape(R, R, *P.shape[1:])
            Y = np.zeros_like(P, dtype=np.float64)
            for c in range(3):
                for dr in (-1, 0, 1):
                    for ds in (-1, 0, 1):
                        rr = np.clip(np.arange(R) + dr, 0, R - 1); ss = np.clip(np.arange(R) + ds, 0, R - 1)
                        nb = Pg[rr][:, ss][..., c].reshape(R * R, -1)
                        Y[..., c] += Wcs[c][dr + 1, ds + 1][:, None] * nb
            return Y
        orig_fit = fitting.fit_ggx
        def predict(rig, pos, res, weights, cam):
            w = np.zeros((weights.shape[0], rig.num_leds, 3), np.float32)
            w[:, np.flatnonzero(~np.asarray(rig.is_bottom))] = weights
            params = dict(normal=res.normal, tangent=res.tangent, rho_d=res.rho_d, rho_s=res.rho_s,
                          alpha_x=res.alpha_x, alpha_y=res.alpha_y)
            m = _tw.measurements(rig, pos.astype(np.float32), patterns=w, transparency=np.zeros(len(pos)),
                                 convention="physical", camera=cam, visibility=True, device="cpu", **params)
            return m.astype(np.float64) * LUMITEXEL_SCALE
        def fit_ggx(rig, positions, lumitexels, *, lines=None, line_weights=None, secondary=None, grid_shape=None, config=fitting.FitConfig()):
            res = orig_fit(rig, positions, lumitexels, lines=lines, line_weights=line_weights, secondary=secondary, grid_shape=grid_shape, config=config)
            meas, grid = stash["meas"], stash["grid"]
            R = grid.resolution
            cams = [rig.camera(c) for c in rig.cameras]
            W0 = footprint(rig, grid, cams[0], meas.pixel_primary.astype(np.float64))
            W1 = footprint(rig, grid, cams[1], meas.pixel_secondary.astype(np.float64))
            tot = [w.sum(axis=(0, 1)) for w in W0]
            print("footprint: centre weight median", [float(np.median(w[1, 1])) for w in W0], "sum", [float(np.median(t)) for t in tot], file=sys.stderr)
            for _ in range(int(os.environ.get("FP_ITERS", "1"))):
                P0 = predict(rig, positions, res, line_weights, cams[0].name)
                P1 = predict(rig, positions, res, secondary[1], cams[1].name)
                s0 = through(W0, P0, R) - P0
                s1 = through(W1, P1, R) - P1
                print("spill rms rel", float(np.sqrt(np.mean((s0 / np.maximum(P0, 1e-6)) ** 2))), file=sys.stderr)
                res = orig_fit(rig, positions, lumitexels, lines=np.maximum(lines - s0, 0).astype(np.float32), line_weights=line_weights,
                               secondary=(np.maximum(secondary[0] - s1, 0).astype(np.float32), secondary[1]), grid_shape=grid_shape, config=config)
            return res
        fitting.fit_ggx = fit_ggx
    if "var" in mode:
        # per pixel and colour: the bilinear value unless it differs from the Malvar-He-Cutler value by more than
        # Z standard deviations of that difference, computed exactly from the HDR merge's per-photosite variance
        # (1 / weights_sum of the stored raw frames, merged again)
        from twin.capture.session import CaptureSession, photo_stem
        from twin.camera.bayer import demosaic, malvar2004
        from twin.camera.hdr import merge_hdr_numpy
        import twin as _tw
        Z = 3.0
        sensor = _tw.load_rig("mini").camera(next(iter(_tw.load_rig("mini").cameras))).sensor
        op = lambda m: malvar2004(m, sensor.bayer) - demosaic(m, sensor.bayer)
        orig_photo = CaptureSession.photo
        stats = []
        def photo(self, k, c):
            img = orig_photo(self, k, c)
            rec = self.photos[photo_stem(k, c)]
            m = merge_hdr_numpy(self.raw_frames(k, c), rec["exposures_s"], sensor)
            with np.errstate(divide="ignore"):
                var = np.where(m.weights_sum > 0, 1.0 / m.weights_sum.astype(np.float64), 0.0)
            mos = m.mosaic.astype(np.float64)
            H, W = mos.shape
            d = op(mos)
            sd2 = np.zeros((H, W, 3))
            sq = np.sqrt(var)
            for i0 in range(6):
                for j0 in range(6):
                    M = np.zeros((H, W)); M[i0::6, j0::6] = 1.0
                    sd2 += op(M * sq) ** 2
            sharp = img + d
            flag = np.abs(d) > Z * np.sqrt(sd2)
            stats.append(flag.mean())
            return np.where(flag, sharp, img).astype(np.float32)
        CaptureSession.photo = photo
        import atexit
        atexit.register(lambda: print("flagged fraction mean %.4f" % np.mean(stats), file=sys.stderr))
    if "hyb" in mode:
        # per pixel and colour: the bilinear value unless it differs from the Malvar-He-Cutler value by more than
        # Z robust standard deviations (1.4826 MAD over the photo) of that difference
        import reconstruction.extraction as ex
        from twin.camera.bayer import cfa_index, malvar2004
        Z = 3.0
        orig_corrected = ex.corrected
        def corrected(img, camera, calibration=None):
            ch = cfa_index(camera.sensor.bayer, camera.height, camera.width)
            mos = np.take_along_axis(img.astype(np.float64), ch[..., None], 2)[..., 0]
            sharp = malvar2004(mos, camera.sensor.bayer)
            d = sharp - img
            if "loc" in mode:  # shot noise: the difference's sd grows as the square root of the signal
                level = np.sqrt(np.maximum(img, 1e-3 * img.max()))
                d = d / level
            sd = np.empty(3)
            for c in range(3):  # over the pixels that interpolate colour c (its own sites have d = 0)
                dc = d[..., c][ch != c]
                sd[c] = 1.4826 * np.median(np.abs(dc - np.median(dc)))
            out = np.where(np.abs(d) > Z * sd, sharp, img).astype(np.float32)
            return orig_corrected(out, camera, calibration)
        ex.corrected = corrected
    import twin
    from hemicube.validate import end_to_end
    t = time.time()
    metrics, rows, _ = end_to_end(twin.load_rig("mini"), sample, "cpu", outdir, None, 1, False,
                                  **({} if frames is None else {"frames": frames}))
    print(json.dumps({"sample": sample, "mode": mode, "s": time.time() - t,
                      "rows": [(r["metric"], round(float(r["value"]), 4), r["passed"]) for r in rows]}))

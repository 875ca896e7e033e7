"""The shared set-up of issue #14's refit scripts on paper (docs/bench/*_2026-11-27.py; a record of how their numbers
were measured, not part of the pipeline). One pipeline run's fit inputs, DUMP, pickled by
`DUMP=... python docs/bench/footprint_coupled_2026-11-26.py SAMPLE OUT` (its capture is OUT/capture), the capture's
true maps on the texture grid, each stock texel's chessboard distance to the nearest ink or foil texel (stock: true
alpha > 0.3; paper's stock is 0.45-0.52, its ink and foil below 0.1), and the exact photos: the forward model at the
texel centres with the true maps as the metrics resample them, under the capture's LED weights."""
import pickle

import numpy as np
from scipy import ndimage

import twin
from reconstruction.data import LUMITEXEL_SCALE
from reconstruction.extraction import TextureGrid
from reconstruction.metrics import map_errors, resample_maps, truth_coverage
from reconstruction.validation import _map_params
from twin.capture.session import CaptureSession

PHOTO_WEIGHT = 400.0  # FitConfig.lambda_lines as the pipeline sets it for four frames an exposure


class Edges:
    def __init__(self, dump: str, capture: str):
        self.d = pickle.load(open(dump, "rb"))
        self.rig = twin.load_rig("mini")
        self.grid = TextureGrid(*self.d["grid"])
        self.R = self.grid.resolution
        true_maps = CaptureSession.open(capture).ground_truth_maps()
        self.truth = resample_maps(true_maps, self.grid.size_mm, self.R)
        self.mask = truth_coverage(true_maps, self.grid.size_mm, self.R)
        self.stock = self.truth.alpha[..., 0] > 0.3
        self.dist = ndimage.distance_transform_cdt(self.stock, metric="chessboard")  # (R, R)
        dist = self.dist
        self.classes = {"d0": ~self.stock, "d1": dist == 1, "d2": dist == 2, "d3-4": (dist >= 3) & (dist <= 4),
                        "d5+": dist >= 5}
        self.cams = list(self.rig.cameras)[:2]

    def exact(self, weights_upper, camera, **params):
        """(N, K, 3) the exact photos under the upper-LED weights (K, L_upper, 3), in network units; `params` replace
        true maps' (e.g. rho_d=0 for the specular part)."""
        upper = np.flatnonzero(~np.asarray(self.rig.is_bottom))
        W = np.zeros((weights_upper.shape[0], len(self.rig.is_bottom), 3), np.float32)
        W[:, upper] = weights_upper
        p = {**_map_params(self.truth), **params}
        pos = self.d["positions"].astype(np.float32)
        return twin.measurements(self.rig, pos, patterns=W, camera=camera, convention="physical", visibility=True,
                                 device="cpu", transparency=np.zeros(len(pos)), **p) * np.float32(LUMITEXEL_SCALE)

    def fit(self, lines=None, secondary=None, **config):
        """The pipeline's fit of the dump's inputs, its photos replaced where given and FitConfig's fields by `config`:
        (FitResult, maps, map_errors)."""
        from dataclasses import replace

        import reconstruction.fitting as fitting

        d = self.d
        res = fitting.fit_ggx(self.rig, d["positions"], d["lumitexels"],
                              lines=d["lines"] if lines is None else lines, line_weights=d["line_weights"],
                              secondary=(d["secondary"][0] if secondary is None else secondary, d["secondary"][1]),
                              grid_shape=d["grid_shape"], config=replace(d["config"], **{"lambda_lines": PHOTO_WEIGHT, **config}))
        maps = fitting.to_maps(res, (self.R, self.R), self.grid.size_mm)
        return res, maps, map_errors(self.truth, maps, mask=self.mask)

    def by_class(self, maps, digits: int = 1, classes=None) -> dict:
        """Per distance class: [alpha_x %, alpha_y % (medians of the relative errors), median log alpha ratio]."""
        ex = np.abs(maps.alpha / self.truth.alpha - 1) * 100
        signed = np.log(maps.alpha / self.truth.alpha).mean(-1)
        return {k: [round(float(np.median(ex[..., 0][c])), digits), round(float(np.median(ex[..., 1][c])), digits),
                    round(float(np.median(signed[c])), 3)] for k, c in (classes or self.classes).items()}

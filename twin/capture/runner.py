"""`hemicube capture`: run the capture plan (twin.capture.plan) on a device backend (twin.capture.backends)
into a session folder (twin.capture.session), resuming a killed run there."""
from __future__ import annotations

import hashlib
from dataclasses import asdict
from pathlib import Path

import numpy as np

from twin.capture.plan import (BRACKET, BRACKET_RATIO, EXPOSURE_LIMITS_S, CaptureError, build_patterns, frame_id,
                               paper_plan)
from twin.capture.session import FORMAT_NAME, FORMAT_VERSION, CaptureSession


def capture(rig, sample: str, output, *, seed: int = 0, backend: str = "sim", device: str = "cpu",
            resolution: int = 128, learned=None, progress: bool = True) -> Path:
    """Run the plan into `output` (resuming a killed run there). Returns the folder. Everything that can be
    checked is checked before the folder is made; a folder this call made is removed again when it fails
    before its first photo."""
    from twin.camera.hdr import choose_bracket, merge_hdr
    from twin.capture.backends import BACKENDS
    from twin.capture.patterns import PatternSet
    from twin.materials.samples import load_sample
    from twin.optics.inputs import check_device

    if backend not in BACKENDS:
        raise CaptureError(f"unknown backend {backend!r}; available: {sorted(BACKENDS)} (real-hardware backends "
                           "are not built yet)")
    check_device(device)
    maps = load_sample(sample, resolution=resolution)
    patterns = build_patterns(rig, learned)
    plan = paper_plan(rig, patterns)
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "rig": rig.name, "rig_digest": rig.digest(),
              "backend": backend, "seed": int(seed), "sample": str(sample), "resolution": int(resolution),
              "patterns_sha256": hashlib.sha256(patterns.to_bytes()).hexdigest(),
              "plan": [asdict(p) for p in plan], "bracket": BRACKET, "bracket_ratio": BRACKET_RATIO,
              "units": {"hdr": "W m^-2 sr^-1 (linear, camera RGB)", "length": "mm"}}
    with CaptureSession.create(output, header) as session:
        session.write_setup(patterns, rig, maps)
        sims = {"sample": BACKENDS[backend](rig, maps, seed=seed, device=device),
                "empty": BACKENDS[backend](rig, None, seed=seed, device=device)}
        for c, cam in enumerate(rig.cameras):
            if not session.pixel_texel_done(c):
                session.write_pixel_texel(c, sims["sample"].surfaces(cam).pixel_texel())

        todo = [p for p in plan if not session.photo_done(p)]
        index = {n: k for k, n in enumerate(patterns.names)}
        for kind in ("sample", "empty"):  # render every pending pattern of a camera in one pass
            for cam in rig.cameras:
                need = sorted({index[p.pattern] for p in todo if p.camera == cam and p.sample == kind})
                if need:
                    sims[kind].prepare(cam, PatternSet(patterns.levels[need],
                                                       tuple(patterns.names[k] for k in need), rig.name))
        bar = _progress(len(plan), len(plan) - len(todo), progress)
        for photo in todo:
            sim = sims[photo.sample]
            sim.show(patterns.levels[index[photo.pattern]])
            sensor = rig.camera(photo.camera).sensor
            exposures = [float(t) for t in np.clip(choose_bracket(max(sim.meter(photo.camera), 1e-12), sensor,
                                                                  n=BRACKET, ratio=BRACKET_RATIO), *EXPOSURE_LIMITS_S)]
            frames = [frame_id(photo, j) for j in range(len(exposures))]
            raws = [sim.grab(photo.camera, t, f) for t, f in zip(exposures, frames)]
            hdr = merge_hdr(raws, exposures, sensor)
            session.write_photo(photo, raws, hdr.radiance,
                                {"pattern": photo.pattern, "camera": photo.camera, "sample": photo.sample,
                                 "exposures_s": exposures, "frames": frames,
                                 "saturated_pixels": int(hdr.saturated_mask.sum())})
            bar.update(1)
        bar.close()
    return session.dir


def _progress(total, done, enabled):
    from tqdm import tqdm

    return tqdm(total=total, initial=done, desc="capture", unit="photo", disable=not enabled)

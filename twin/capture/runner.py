"""`hemicube capture`: run the capture plan (twin.capture.plan) on a device backend (twin.capture.backends)
into a session folder (twin.capture.session), resuming a killed run there."""
from __future__ import annotations

import hashlib
from dataclasses import asdict
from pathlib import Path

from twin.capture.plan import (BRACKET, BRACKET_RATIO, CaptureError, bracket_exposures, build_patterns, frame_id,
                               paper_plan)
from twin.capture.session import FORMAT_NAME, FORMAT_VERSION, CaptureSession


def capture(rig, sample: str, output, *, seed: int = 0, backend: str = "sim", device: str = "cpu",
            resolution: int = 128, learned=None, progress: bool = True, devices: dict | None = None) -> Path:
    """Run the plan into `output` (resuming a killed run there). Returns the folder. `devices` are the
    hardware backend's options (twin.capture.backends.hardware.open_hardware: led, cameras, ...). Everything
    that can be checked, the devices included, is checked before the folder is made; a folder this call made
    is removed again when it fails before its first photo."""
    from twin.camera.hdr import merge_hdr
    from twin.capture.backends import BACKENDS, open_backends
    from twin.capture.patterns import PatternSet
    from twin.materials.samples import load_sample
    from twin.optics.inputs import check_device

    devices = {k: v for k, v in (devices or {}).items() if v is not None}
    if backend not in BACKENDS:
        raise CaptureError(f"unknown backend {backend!r}; available: {sorted(BACKENDS)}")
    if backend == "sim" and devices:
        raise CaptureError(f"{', '.join(sorted(devices))}: options of --backend hardware, not of the simulator")
    check_device(device)
    # the twin renders (and so knows the ground truth) unless real cameras take the photos
    maps = load_sample(sample, resolution=resolution) if devices.get("cameras") != "basler" else None
    patterns = build_patterns(rig, learned)
    plan = paper_plan(rig, patterns)
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "rig": rig.name, "rig_digest": rig.digest(),
              "backend": backend, "seed": int(seed), "sample": str(sample), "resolution": int(resolution),
              "patterns_sha256": hashlib.sha256(patterns.to_bytes()).hexdigest(),
              "plan": [asdict(p) for p in plan], "bracket": BRACKET, "bracket_ratio": BRACKET_RATIO,
              "units": {"hdr": "W m^-2 sr^-1 (linear, camera RGB)", "length": "mm"}}
    if backend != "sim":  # a resume must not mix emulated and real cameras
        header["cameras"] = devices.get("cameras")
    with open_backends(backend, rig, maps, seed=seed, device=device, **devices) as sims, \
            CaptureSession.create(output, header) as session:
        session.write_setup(patterns, rig, maps)
        for c, cam in enumerate(rig.cameras):
            if maps is not None and not session.pixel_texel_done(c):
                session.write_pixel_texel(c, sims["sample"].surfaces(cam).pixel_texel())

        todo = [p for p in plan if not session.photo_done(p)]
        index = {n: k for k, n in enumerate(patterns.names)}
        # Render every pattern of a camera in one pass, all of them whenever one is pending: BLAS does not
        # sum a one-pattern product in the same order as a many-pattern one (the last bit differs, and so may
        # the sensor's Poisson draws), so a resumed photo is bit-identical only if rendered in the same batch.
        for kind in ("sample", "empty"):
            for cam in rig.cameras:
                mine = [p for p in plan if p.camera == cam and p.sample == kind]
                need = sorted({index[p.pattern] for p in mine}) if any(p in todo for p in mine) else []
                if need:
                    sims[kind].prepare(cam, PatternSet(patterns.levels[need],
                                                       tuple(patterns.names[k] for k in need), rig.name))
        bar = _progress(len(plan), len(plan) - len(todo), progress)
        for photo in todo:
            sim = sims[photo.sample]
            shown = sim.show(patterns.levels[index[photo.pattern]])
            sensor = rig.camera(photo.camera).sensor
            exposures = bracket_exposures(sim.meter(photo.camera), sensor)
            frames = [frame_id(photo, j) for j in range(len(exposures))]
            raws, exposures, grabbed = sim.grab_bracket(photo.camera, exposures, frames)
            hdr = merge_hdr(raws, exposures, sensor)
            session.write_photo(photo, raws, hdr.radiance,
                                {"pattern": photo.pattern, "camera": photo.camera, "sample": photo.sample,
                                 "exposures_s": exposures, "frames": frames,
                                 "saturated_pixels": int(hdr.saturated_mask.sum()), **shown, **grabbed})
            bar.update(1)
        bar.close()
    return session.dir


def _progress(total, done, enabled):
    from tqdm import tqdm

    return tqdm(total=total, initial=done, desc="capture", unit="photo", disable=not enabled)

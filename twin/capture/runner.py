"""`hemicube capture`: run the capture plan (twin.capture.plan) on a device backend (twin.capture.backends)
into a session folder (twin.capture.session), resuming a killed run there.

`photos` is the capture itself: it renders every pending pattern of a camera in one pass, then takes each
photo (meter, exposure bracket, raw frames, HDR merge) on the backend's device; a photo whose bracket is
implausible (twin.capture.plausibility) is taken again, then refused by name; a photo leaves the device
only when `capture` writes its files. `hemicube bench capture` times the same generator.

Files: a finished photo (its raw frames too with `raw`) is copied to the host (`HostCopies`: on CUDA into reused
page-locked buffers, the fast transfer) and handed to one of WRITERS threads (packing, EXR writing and checksums
release the GIL), so the device takes the next photos while earlier ones are written. `capture_bytes` gives the
bytes its photos write, from the plan alone.
"""
from __future__ import annotations

import hashlib
import os
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import asdict
from pathlib import Path

import numpy as np

from twin.capture.plan import (BRACKET, BRACKET_RATIO, DEFAULT_FRAMES, CaptureError, DeviceError, build_patterns,
                               check_frames, exposure_frames, frame_id, frames_per_photo, paper_plan, photo_exposures)
from twin.capture.plausibility import PHOTO_ATTEMPTS, judge_bracket
from twin.capture.session import FORMAT_NAME, FORMAT_VERSION, CaptureSession, photo_bytes, photo_stem

WRITERS = max(1, min(8, os.cpu_count() or 1))


class HostCopies:
    """Host (numpy) copies of device arrays in numbered slots: on CUDA each slot is a page-locked buffer,
    reused by the next copy into that slot (its previous contents must be consumed by then); CPU arrays are
    copied plainly."""

    def __init__(self):
        self._pinned = {}

    def __call__(self, slot: int, *arrays) -> list[np.ndarray]:
        import warp as wp

        out = []
        for i, a in enumerate(arrays):
            if not a.device.is_cuda:
                out.append(a.numpy().copy())
                continue
            key = (slot, i, a.shape, a.dtype)
            if key not in self._pinned:
                self._pinned[key] = wp.empty(a.shape, dtype=a.dtype, device="cpu", pinned=True)
            wp.copy(self._pinned[key], a)
            wp.synchronize_stream(wp.get_stream(a.device))
            out.append(self._pinned[key].numpy())
        return out


def open_backends(rig, maps, backend: str, seed: int, device: str, devices: dict | None = None, truth=None):
    """The plan's two scenes, the sample and the empty board (the transparency reference), on `backend`, open
    for a `with` block; `devices` are the hardware backend's options (twin.capture.backends.hardware); `truth`
    the simulator's true device (see `capture`)."""
    from twin.capture.backends import BACKENDS, open_backends as open_named

    devices = devices or {}
    if backend not in BACKENDS:
        raise CaptureError(f"unknown backend {backend!r}; available: {sorted(BACKENDS)}")
    if backend == "sim" and devices:
        raise CaptureError(f"{', '.join(sorted(devices))}: options of --backend hardware, not of the simulator")
    if truth is not None:
        if backend != "sim":
            raise CaptureError("--truth is the simulator's true device; the hardware is its own")
        return open_named(backend, rig, maps, seed=seed, device=device, truth=truth)
    return open_named(backend, rig, maps, seed=seed, device=device, **devices)


def prepare(rig, sims: dict, patterns, todo) -> None:
    """Get the backends ready for the photos `todo`: every pattern they show, a camera's in one pass."""
    from twin.capture.patterns import PatternSet

    index = {n: k for k, n in enumerate(patterns.names)}
    for kind in ("sample", "empty"):
        for cam in rig.cameras:
            need = sorted({index[p.pattern] for p in todo if p.camera == cam and p.sample == kind})
            if need:
                sims[kind].prepare(cam, PatternSet(patterns.levels[need], tuple(patterns.names[k] for k in need),
                                                   rig.name))


def photos(rig, sims: dict, patterns, todo, device: str, stage=None, frames: int = DEFAULT_FRAMES):
    """Take the photos `todo` (plan entries), each exposure of the bracket its exposure_frames(frames) times
    (twin.capture.plan): yields (photo, raws (n, H, W) uint16 Warp array, HDR merge
    (twin.camera.hdr.merge_hdr_device's dict), record), all on `device`.
    A take whose bracket is implausible (twin.capture.plausibility.judge_bracket) is taken again, at most
    PHOTO_ATTEMPTS times in all, the reasons kept in the record's "retakes"; then CaptureError names the photo.
    `stage(name)`, when given, is a context manager around each stage ("render", "sensor", "check", "hdr"): the
    bench's timer."""
    from twin.camera.hdr import merge_hdr_device

    stage = stage or (lambda name: nullcontext())
    index = {n: k for k, n in enumerate(patterns.names)}
    with stage("render"):
        prepare(rig, sims, patterns, todo)
    for photo in todo:
        cam = rig.camera(photo.camera)
        name = photo_stem(photo.index, photo.camera_index)
        refused = []  # the reasons of the takes refused before the one kept, theirs included
        for _ in range(PHOTO_ATTEMPTS):
            try:
                raws, exposures, ids, shown, grabbed = _take(sims[photo.sample], cam, photo,
                                                             patterns.levels[index[photo.pattern]], device, frames,
                                                             stage)
            except DeviceError as e:  # the devices' retries are spent: stop at this photo, by name
                raise DeviceError(f"photo {name}: {e}") from None
            with stage("check"):
                reason = judge_bracket(raws, exposures, cam.sensor).reason
            if reason is None:
                break
            refused += grabbed.get("retakes", []) + [f"implausible: {reason}"]
        else:
            raise CaptureError(f"photo {name} ({photo.pattern}, camera {photo.camera}) is implausible after "
                               f"{PHOTO_ATTEMPTS} takes: {reason}")
        with stage("hdr"):
            hdr = merge_hdr_device(raws, exposures, cam.sensor)
            record = {"pattern": photo.pattern, "camera": photo.camera, "sample": photo.sample,
                      "exposures_s": exposures, "frames": ids,
                      "saturated_pixels": int(hdr["saturated_count"].numpy()[0]), **shown, **grabbed}
        if refused:
            record["retakes"] = refused + record.get("retakes", [])
        yield photo, raws, hdr, record


def _take(sim, cam, photo, levels, device, frames, stage):
    """One take of a photo: light the pattern, meter, grab the bracket. Returns (raws (n, H, W) uint16 Warp
    array, the exposures as the camera applied them, frame ids, what `show` and `grab_bracket` report)."""
    import warp as wp

    with stage("sensor"):
        shown = sim.show(levels)
        exposures = photo_exposures(sim.meter(photo.camera), cam.sensor, frames)
        ids = [frame_id(photo, j) for j in range(len(exposures))]
        raws = wp.empty((len(exposures), cam.height, cam.width), dtype=wp.uint16, device=device)
        exposures, grabbed = sim.grab_bracket(photo.camera, exposures, ids, raws)  # as the camera applied
    return raws, exposures, ids, shown, grabbed


SAMPLE_RESOLUTION = 128  # texels per side of a built-in sample's maps when a capture renders it


def capture_header(rig, sample: str, *, seed: int = 0, backend: str = "sim", resolution: int = SAMPLE_RESOLUTION,
                   learned=None, cameras: str | None = None, truth=None, frames: int = DEFAULT_FRAMES,
                   raw: bool = False) -> tuple[dict, object, list]:
    """(the manifest header, the pattern set, the plan) of the capture these arguments describe: what a capture
    folder must hold to be resumed (or, finished, to be reused) for them."""
    patterns = build_patterns(rig, learned)
    plan = paper_plan(rig, patterns)
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "rig": rig.name, "rig_digest": rig.digest(),
              "backend": backend, "seed": int(seed), "sample": str(sample), "resolution": int(resolution),
              "patterns_sha256": hashlib.sha256(patterns.to_bytes()).hexdigest(),
              "plan": [asdict(p) for p in plan], "bracket": BRACKET, "bracket_ratio": BRACKET_RATIO,
              "units": {"hdr": "W m^-2 sr^-1 (linear, camera RGB)", "length": "mm"}}
    if backend != "sim":  # a resume must not mix emulated and real cameras
        header["cameras"] = cameras
    if truth is not None:  # rendered with another rig than the one recorded: say which
        header["simulated_with"] = {"rig": truth.name, "rig_digest": truth.digest()}
    if check_frames(frames) != 1:  # absent: one frame an exposure (so the folders made before this stay resumable)
        header["frames_per_exposure"] = frames
    # each exposure's frames (the shortest's repeated more: twin.capture.plan.SHORTEST_REPEAT); a folder made
    # before that has no such key, so it is not resumed with frames taken another way
    header["exposure_frames"] = exposure_frames(frames)
    if not raw:  # absent: the raw frames are written, as in every folder made before they were optional
        header["raw_frames"] = False
    return header, patterns, plan


def capture_bytes(rig, *, raw: bool = False, frames: int = DEFAULT_FRAMES, learned=None) -> dict:
    """The bytes the photos of `capture(rig, ..., frames=frames, learned=learned, raw=raw)` write, from the plan
    without rendering: {"hdr": the HDR EXRs, "raw": the raw frames (0 without `raw`), "total"}. The rest of the
    folder (manifest, patterns, rig, ground truth) is not counted."""
    sizes = [photo_bytes(rig.camera(p.camera).height, rig.camera(p.camera).width, frames_per_photo(frames))
             for p in paper_plan(rig, build_patterns(rig, learned))]
    hdr = sum(h for h, _ in sizes)
    raws = sum(r for _, r in sizes) if raw else 0
    return {"hdr": hdr, "raw": raws, "total": hdr + raws}


def capture(rig, sample: str, output, *, seed: int = 0, backend: str = "sim", device: str = "cpu",
            resolution: int = SAMPLE_RESOLUTION, learned=None, progress: bool = True, devices: dict | None = None,
            truth=None, frames: int = DEFAULT_FRAMES, break_lock: bool = False, raw: bool = False) -> Path:
    """Run the plan into `output` (resuming a killed run there), each exposure taken `frames` times, the shortest
    twice as often (the HDR merge averages them; twin.capture.plan.bracket_frames). Returns the folder. `raw`: write
    every photo's raw frames too (nothing reconstruction reads; with four frames an exposure, three times the bytes:
    `capture_bytes`); a folder is resumed only with the choice it was made with. `devices`
    are the hardware backend's options (twin.capture.backends.hardware.open_hardware: led, cameras, ...). `truth`
    (simulator only): the rig the twin renders with, the true device, while the folder records `rig`, its
    calibration, as a real device's capture records the calibrated rig (docs/calibration.md); it must be
    `rig`'s device (Rig.layout_digest): differ only in how the cameras record light, in the cameras' lenses and
    poses and in the LEDs' positions, normals, profiles and intensities. Everything that can
    be checked, the devices included, is checked before the folder is made; a folder this call made is removed
    again when it fails before its first photo. `break_lock`: take the folder's lock that another host recorded
    (twin.lock)."""
    from twin.materials.samples import load_sample
    from twin.optics.inputs import check_device

    device = check_device(device)
    devices = {k: v for k, v in (devices or {}).items() if v is not None}
    if truth is not None and truth.layout_digest() != rig.layout_digest():
        raise CaptureError(f"--truth {truth.name!r} differs from rig {rig.name!r} in more than a calibration "
                           "measures (how the cameras record light, their lenses and poses; the LEDs' positions, "
                           "normals, profiles and intensities): the LED layout, sample plane, frame or cameras' pixel "
                           "grids differ, so it is not a calibration of it")
    # the twin renders (and so knows the ground truth) unless real cameras take the photos
    maps = load_sample(sample, resolution=resolution) if devices.get("cameras") != "basler" else None
    header, patterns, plan = capture_header(rig, sample, seed=seed, backend=backend, resolution=resolution,
                                            learned=learned, cameras=devices.get("cameras"), truth=truth,
                                            frames=frames, raw=raw)
    with open_backends(rig, maps, backend, seed, device, devices, truth) as sims, \
            CaptureSession.create(output, header, break_lock) as session:
        session.write_setup(patterns, rig, maps)
        for c, cam in enumerate(rig.cameras):
            if maps is not None and not session.pixel_texel_done(c):
                session.write_pixel_texel(c, sims["sample"].surfaces(cam).pixel_texel())
        todo = [p for p in plan if not session.photo_done(p)]
        bar = _progress(len(plan), len(plan) - len(todo), progress)
        host = HostCopies()
        slots = [None] * (2 * WRITERS)  # a slot's buffers are reused once its photo is written
        with ThreadPoolExecutor(WRITERS) as pool:
            for n, (photo, raws, hdr, record) in enumerate(photos(rig, sims, patterns, todo, device, frames=frames)):
                k = n % len(slots)
                if slots[k] is not None:
                    slots[k].result()
                if raw:
                    raws_h, rad_h = host(k, raws, hdr["radiance"])
                    raws_h = list(raws_h)
                else:  # the raw frames stay on the device
                    raws_h, (rad_h,) = None, host(k, hdr["radiance"])
                slots[k] = pool.submit(session.write_photo, photo, raws_h, rad_h, record)
                slots[k].add_done_callback(lambda f: bar.update(1))
            for f in slots:
                if f is not None:
                    f.result()  # re-raises a writer's error
        bar.close()
    return session.dir


def _progress(total, done, enabled):
    from twin.progress import progress_bar

    return progress_bar(total=total, initial=done, desc="capture", unit="photo", enabled=enabled)

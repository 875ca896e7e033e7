"""The capture plan and session folders (`hemicube capture`).

Plan (reference §6.3 indices, extended by the photos the reference takes separately):

    k 0-63     learned patterns as 32 (+, -) pairs          cameras 0 and 1
    k 64-127   the 64 linear lights                         camera 0
    k 128      all bottom LEDs (transparency)               camera 0
    k 129      uniform light (two-view alignment)           cameras 0 and 1
    k 130      all bottom LEDs, empty board (reference for transparency: transparency = k128 / k130)

Each photo is an exposure bracket of raw frames merged to linear HDR (twin.hdr). A session folder:

    manifest.json               format, version, rig digest, backend, seed, sample, plan (per photo: pattern
                                name, camera, exposures, frame ids), per-file sha256 ("files")
    patterns.npz                every pattern used (twin.patterns format)
    rig/                        the rig folder (the capture is self-contained)
    img{k:05d}_cam{c:02d}.exr   merged HDR radiance, linear float32 RGB, W m^-2 sr^-1
    raw/img{k:05d}_cam{c:02d}_e{j}.BayerRG12p   raw frames, GenICam PFNC BayerRG12p (12-bit packed)
    ground_truth/maps/          the sample's true SVBRDF maps (OpenSVBRDF contract)
    ground_truth/pixel_texel_cam{c:02d}.npy   (H, W, 2) float32 true texel (row, col) of each pixel, NaN off it

Every file is written atomically, and the manifest (rewritten atomically after each photo) lists a file
only once it is complete. Re-running on the same folder verifies the listed files' checksums, keeps the
verified photos and takes the rest; a folder made with another rig, sample, seed or plan is refused.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from . import pattern_sets
from .atomic import atomic_path, file_sha256, write_bytes_atomic

FORMAT_NAME = "hemicube-capture"
FORMAT_VERSION = 1
BRACKET = 3  # raw frames per photo
BRACKET_RATIO = 8.0
EXPOSURE_LIMITS_S = (20e-6, 1.0)  # the camera's exposure range used by the plan (a2A5328-15ucPRO: 20 us up)


class CaptureError(ValueError):
    pass


@dataclass(frozen=True)
class Photo:
    index: int
    camera: str
    camera_index: int
    pattern: str
    sample: str  # "sample" or "empty"

    @property
    def stem(self) -> str:
        return f"img{self.index:05d}_cam{self.camera_index:02d}"


def build_patterns(rig, learned=None):
    """The plan's pattern set: the learned frames given, else those of the network shipped for this rig
    (reconstruction.pretrained; the mini rig's), else a seeded placeholder."""
    if learned is None:
        from reconstruction.pretrained import pretrained_patterns

        learned = pretrained_patterns(rig) or pattern_sets.placeholder_learned(rig)
    if learned.num_patterns != 64:
        raise CaptureError(f"the plan needs 64 learned frames (32 signed pairs), got {learned.num_patterns}")
    sets = [learned, pattern_sets.linear_lights(rig), pattern_sets.uniform(rig)]
    if rig.is_bottom.any():
        sets.append(pattern_sets.bottom_only(rig))
    return pattern_sets.concatenate(sets, rig.name, note=learned.note)


def paper_plan(rig, patterns) -> list[Photo]:
    cams = list(rig.cameras)
    names = patterns.names
    plan = []
    for k in range(64):
        plan += [Photo(k, cams[c], c, names[k], "sample") for c in range(len(cams))]
    plan += [Photo(64 + k, cams[0], 0, f"line_{k:02d}", "sample") for k in range(64)]
    if "bottom" in names:
        plan.append(Photo(128, cams[0], 0, "bottom", "sample"))
    plan += [Photo(129, cams[c], c, "uniform", "sample") for c in range(len(cams))]
    if "bottom" in names:
        plan.append(Photo(130, cams[0], 0, "bottom", "empty"))
    return plan


def _frame_id(photo: Photo, j: int) -> int:
    """Counter for the sensor's random stream: unique per (photo, camera, exposure), not per run order."""
    return (photo.index * 8 + photo.camera_index) * 16 + j


class Session:
    """A capture folder and its manifest."""

    def __init__(self, directory, header: dict):
        self.dir = Path(directory)
        self.header = header
        self.manifest_path = self.dir / "manifest.json"
        self.files: dict[str, str] = {}
        self.photos: dict[str, dict] = {}
        if self.manifest_path.exists():
            try:
                old = json.loads(self.manifest_path.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError) as e:
                raise CaptureError(f"{self.manifest_path}: unreadable manifest ({e}); move the folder away") from None
            mismatch = [k for k in header if old.get(k) != header[k]]
            if mismatch:
                raise CaptureError(f"{self.dir} holds a different capture ({', '.join(mismatch)} differ); "
                                   "choose another folder")
            self.files = dict(old.get("files", {}))
            self.photos = dict(old.get("photos", {}))
        self.dir.mkdir(parents=True, exist_ok=True)

    def verified(self, rel: str) -> bool:
        p = self.dir / rel
        return rel in self.files and p.is_file() and file_sha256(p) == self.files[rel]

    def photo_done(self, photo: Photo) -> bool:
        rec = self.photos.get(photo.stem)
        return rec is not None and all(self.verified(r) for r in rec["files"])

    def write(self, rel: str, data: bytes) -> None:
        write_bytes_atomic(self.dir / rel, data)
        self.files[rel] = hashlib.sha256(data).hexdigest()

    def write_file(self, rel: str, writer) -> None:
        """`writer(tmp_path)` writes the file; it is renamed into place and checksummed."""
        path = self.dir / rel
        with atomic_path(path) as tmp:
            writer(tmp)
        self.files[rel] = file_sha256(path)

    def record(self, photo: Photo, rec: dict) -> None:
        self.photos[photo.stem] = rec
        self.save()

    def save(self) -> None:
        doc = {**self.header, "photos": self.photos, "files": self.files}
        write_bytes_atomic(self.manifest_path, json.dumps(doc, sort_keys=True, separators=(",", ":")).encode())


def verify(directory) -> list[str]:
    """Files of a session whose checksum does not match the manifest (empty when all verify)."""
    d = Path(directory)
    doc = json.loads((d / "manifest.json").read_text())
    return [rel for rel, h in doc["files"].items() if not (d / rel).is_file() or file_sha256(d / rel) != h]


def capture(rig, sample: str, output, *, seed: int = 0, backend: str = "sim", device: str = "cpu",
            resolution: int = 128, learned=None, progress: bool = True) -> Path:
    """Run the plan into `output` (resuming a killed run there). Returns the folder."""
    from .backends import BACKENDS
    from .bayer import pack_bayer_rg12p
    from .exr import write_rgb_exr
    from .hdr import choose_bracket, merge_hdr
    from .rig_format import save_rig
    from .samples import load_sample, write_maps

    if backend not in BACKENDS:
        raise CaptureError(f"unknown backend {backend!r}; available: {sorted(BACKENDS)} (real-hardware backends "
                           "are not built yet)")
    maps = load_sample(sample, resolution=resolution)
    patterns = build_patterns(rig, learned)
    plan = paper_plan(rig, patterns)
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "rig": rig.name, "rig_digest": rig.digest(),
              "backend": backend, "seed": int(seed), "sample": str(sample), "resolution": int(resolution),
              "patterns_sha256": hashlib.sha256(patterns.to_bytes()).hexdigest(),
              "plan": [asdict(p) for p in plan], "bracket": BRACKET, "bracket_ratio": BRACKET_RATIO,
              "units": {"hdr": "W m^-2 sr^-1 (linear, camera RGB)", "length": "mm"}}
    session = Session(output, header)
    out = session.dir
    if not session.verified("patterns.npz"):
        session.write("patterns.npz", patterns.to_bytes())
    for folder, writer in (("rig", lambda d: save_rig(rig, d, overwrite=True)),
                           ("ground_truth/maps", lambda d: write_maps(maps, d))):
        listed = [r for r in session.files if r.startswith(folder + "/")]
        if not listed or not all(session.verified(r) for r in listed):
            if (out / folder).exists():
                shutil.rmtree(out / folder)
            writer(out / folder)
            for f in sorted((out / folder).iterdir()):
                session.files[f"{folder}/{f.name}"] = file_sha256(f)
    sims = {"sample": BACKENDS[backend](rig, maps, seed=seed, device=device),
            "empty": BACKENDS[backend](rig, None, seed=seed, device=device)}
    for c, cam in enumerate(rig.cameras):
        rel = f"ground_truth/pixel_texel_cam{c:02d}.npy"
        if not session.verified(rel):
            session.write_file(rel, lambda tmp, cam=cam: np.save(tmp, sims["sample"].surfaces(cam).pixel_texel()
                                                                   .astype(np.float32)))
    session.save()

    todo = [p for p in plan if not session.photo_done(p)]
    index = {n: k for k, n in enumerate(patterns.names)}
    for kind in ("sample", "empty"):  # render every pending pattern of a camera in one pass
        for cam in rig.cameras:
            need = sorted({index[p.pattern] for p in todo if p.camera == cam and p.sample == kind})
            if need:
                from .patterns import PatternSet

                sims[kind].prepare(cam, PatternSet(patterns.levels[need], tuple(patterns.names[k] for k in need),
                                                   rig.name))
    bar = _progress(len(plan), len(plan) - len(todo), progress)
    for photo in todo:
        sim = sims[photo.sample]
        sim.show(patterns.levels[index[photo.pattern]])
        sensor = rig.camera(photo.camera).sensor
        exposures = [float(t) for t in np.clip(choose_bracket(max(sim.meter(photo.camera), 1e-12), sensor, n=BRACKET,
                                                               ratio=BRACKET_RATIO), *EXPOSURE_LIMITS_S)]
        files, raws = [], []
        for j, t in enumerate(exposures):
            raw = sim.grab(photo.camera, t, _frame_id(photo, j))
            raws.append(raw)
            rel = f"raw/{photo.stem}_e{j}.BayerRG12p"
            session.write(rel, pack_bayer_rg12p(raw))
            files.append(rel)
        hdr = merge_hdr(raws, exposures, sensor)
        rel = f"{photo.stem}.exr"
        session.write_file(rel, lambda tmp: write_rgb_exr(tmp, hdr.radiance))
        files.append(rel)
        session.record(photo, {"pattern": photo.pattern, "camera": photo.camera, "sample": photo.sample,
                               "exposures_s": exposures, "frames": [_frame_id(photo, j) for j in range(len(raws))],
                               "saturated_pixels": int(hdr.saturated_mask.sum()),
                               "raw_shape": list(raws[0].shape), "files": files})
        bar.update(1)
    bar.close()
    return out


def _progress(total, done, enabled):
    from tqdm import tqdm

    return tqdm(total=total, initial=done, desc="capture", unit="photo", disable=not enabled)

"""The capture session folder, and its one owner: the capture loop writes it through `CaptureSession.create`,
reconstruction and validation read it through `CaptureSession.open`; no other module knows its file names.

    manifest.json               format, version, rig digest, backend, seed, sample, plan (per photo: pattern
                                name, camera, exposures, frame ids), per-file sha256 ("files")
    patterns.npz                every pattern used (twin.capture.patterns format)
    rig/                        the rig folder (the capture is self-contained)
    img{k:05d}_cam{c:02d}.exr   merged HDR radiance, linear float32 RGB, W m^-2 sr^-1
    raw/img{k:05d}_cam{c:02d}_e{j}.BayerRG12p   raw frames, GenICam PFNC BayerRG12p (12-bit packed); only in a
                                capture made with --raw (the header's raw_frames is false in one made without)
    ground_truth/maps/          the sample's true SVBRDF maps (OpenSVBRDF contract; a twin capture only)
    ground_truth/pixel_texel_cam{c:02d}.npy   (H, W, 2) float32 true texel (row, col) of each pixel, NaN off it
    .lock                       the one writer's lock while a capture runs (twin.lock)

Writing: every file is written atomically, and the manifest (rewritten atomically after each photo) lists a
file only once it is complete, so a killed capture resumes: re-running removes the temporary files the killed
writer left (twin.atomic's, and nothing else), verifies the listed files, keeps the verified photos and takes the
rest. A folder made with another rig, sample, seed or plan is refused, and so is a second writer while the first
runs (twin.lock: a killed writer's lock is stale, one recorded by another host is taken with --break-lock).
A folder this writer created is removed again when the capture fails before its first photo.
Reading: each file is checked against the manifest's sha256 as it is read; the first that fails is named.
Both: the manifest's paths are checked to lie inside the folder before anything is opened, and a symbolic link
inside the folder is refused by name, never followed (twin.paths).
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from twin.atomic import atomic_path, file_sha256, remove_leftovers, write_bytes_atomic
from twin.capture.plan import CaptureError, Photo, check_frames
from twin.lock import LOCK, FolderLock, LockError
from twin.outputs import Kind
from twin.paths import files_below, inside, relative_path

FORMAT_NAME = "hemicube-capture"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
PATTERNS = "patterns.npz"
RIG = "rig"
MAPS = "ground_truth/maps"
CAPTURE_FOLDER = Kind("a capture folder", (MANIFEST,))  # what `hemicube capture -o` resumes (twin.outputs)
VERIFIERS = max(1, min(8, os.cpu_count() or 1))  # threads that checksum a capture's files (verify)


def photo_stem(index: int, camera_index: int) -> str:
    return f"img{index:05d}_cam{camera_index:02d}"


def _photo_file(index: int, camera_index: int) -> str:
    return f"{photo_stem(index, camera_index)}.exr"


def _raw_file(index: int, camera_index: int, j: int) -> str:
    return f"raw/{photo_stem(index, camera_index)}_e{j}.BayerRG12p"


def _pixel_texel_file(camera_index: int) -> str:
    return f"ground_truth/pixel_texel_cam{camera_index:02d}.npy"


def photo_bytes(height: int, width: int, raw_frames: int) -> tuple[int, int]:
    """(the HDR EXR's bytes, its `raw_frames` raw frames' bytes) of one photo of a (height, width) camera, as
    `CaptureSession.write_photo` writes them."""
    from twin.camera.bayer import bayer_rg12p_bytes
    from twin.materials.exr import rgb_exr_bytes

    return rgb_exr_bytes(height, width), raw_frames * bayer_rg12p_bytes(height, width)


BODY = ("photos", "files")  # a manifest's keys besides its header's (CaptureSession.save)


def _differing(old: dict, header: dict) -> list[str]:
    """The header keys whose value a manifest `old` does not share: those of `header`, and the optional ones
    (`simulated_with`, `cameras`, `frames_per_exposure`, `raw_frames`: absent unless set) that only `old` has."""
    keys = list(header) + [k for k in old if k not in header and k not in BODY]
    return [k for k in keys if old.get(k) != header.get(k)]


def _keeps_raw_frames(header: dict) -> bool:
    return header.get("raw_frames", True) is not False


def _read_manifest(directory: Path) -> dict:
    """The manifest of a capture folder holding no symbolic link, its listed paths checked (_check_listed)."""
    files_below(directory, CaptureError)
    path = directory / MANIFEST
    if not path.is_file():
        raise CaptureError(f"{directory}: not a capture folder (no {MANIFEST})")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CaptureError(f"{path}: unreadable manifest ({e})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
        raise CaptureError(f"{path}: not a {FORMAT_NAME} manifest")
    if doc.get("version") != FORMAT_VERSION:
        raise CaptureError(f"{path}: unknown capture format version {doc.get('version')!r}; this twin reads "
                           f"version {FORMAT_VERSION}")
    _check_listed(doc, path)
    return doc


def _check_listed(doc: dict, path: Path) -> None:
    """Every path the manifest lists (its files, each photo's files) lies inside the folder, or a CaptureError."""
    files, photos = doc.get("files", {}), doc.get("photos", {})
    if not (isinstance(files, dict) and isinstance(photos, dict)
            and all(isinstance(r, dict) and isinstance(r.get("files", []), list) for r in photos.values())):
        raise CaptureError(f"{path}: malformed manifest (its files and photos are not the maps this twin writes)")
    for rel in [*files, *(f for r in photos.values() for f in r.get("files", []))]:
        relative_path(rel, path, CaptureError)


class CaptureSession:
    """A capture folder and its manifest. Build one with `create` (the writer) or `open` (a reader)."""

    def __init__(self, directory: Path, header: dict, files: dict, photos: dict):
        self.dir = Path(directory)
        self.header = header
        self.files: dict[str, str] = files
        self.photos: dict[str, dict] = photos
        self._lock: FolderLock | None = None
        self._created = False
        self._mutex = threading.Lock()  # write_photo may run in several writer threads

    # --- reading --------------------------------------------------------------------------------------
    @classmethod
    def open(cls, directory) -> "CaptureSession":
        d = Path(directory)
        doc = _read_manifest(d)
        files, photos = doc.pop("files", {}), doc.pop("photos", {})
        return cls(d, doc, dict(files), dict(photos))

    @property
    def rig_name(self) -> str:
        return self.header["rig"]

    @property
    def rig_digest(self) -> str:
        return self.header["rig_digest"]

    @property
    def sample(self) -> str:
        return self.header.get("sample", "a capture")

    @property
    def frames_per_exposure(self) -> int:
        """Raw frames taken of each of a photo's longer exposures, the shortest's being SHORTEST_REPEAT times as many
        where the header lists `exposure_frames` (twin.capture.plan; the header's key; absent: one, as in every folder
        made before frame averaging); a value out of range is a CaptureError naming the folder."""
        frames = self.header.get("frames_per_exposure", 1)
        try:
            return check_frames(frames)
        except CaptureError as e:
            raise CaptureError(f"{self.dir}: manifest's frames_per_exposure {frames!r}: {e}") from None

    @property
    def keeps_raw_frames(self) -> bool:
        """Whether the capture writes its photos' raw frames: the header's `raw_frames`, false in a capture made
        without --raw (absent: true, as in every folder made before raw frames were optional)."""
        return _keeps_raw_frames(self.header)

    def shown_patterns(self, camera_index: int = 0) -> dict[int, str]:
        """Photo index -> the name of the pattern it was taken under (the manifest's plan), for one camera."""
        return {p["index"]: p["pattern"] for p in self.header.get("plan", []) if p["camera_index"] == camera_index}

    def content_digest(self) -> str:
        """sha256 of the manifest's header and its files' checksums: two folders with one digest hold the same
        capture, byte for byte (a reconstruction's stages are keyed on it, reconstruction.output)."""
        doc = json.dumps({"header": self.header, "files": self.files}, sort_keys=True, default=str)
        return hashlib.sha256(doc.encode()).hexdigest()

    def _path(self, rel: str) -> Path:
        """The folder's file `rel`, reached through no symbolic link (twin.paths.inside)."""
        return inside(self.dir, rel, CaptureError)

    def verified(self, rel: str) -> bool:
        p = self._path(rel)
        return rel in self.files and p.is_file() and file_sha256(p) == self.files[rel]

    def _checked(self, rel: str) -> Path:
        """The path of a listed file whose bytes match the manifest, else a CaptureError naming it."""
        path = self._path(rel)
        if rel not in self.files:
            raise CaptureError(f"{self.dir}: {rel} is not in the manifest (an incomplete capture? re-run "
                               "`hemicube capture` on the folder to finish it)")
        if not path.is_file():
            raise CaptureError(f"{path}: listed in the manifest but missing")
        if file_sha256(path) != self.files[rel]:
            raise CaptureError(f"{path}: fails its checksum (changed after the capture wrote it)")
        return path

    def _checked_folder(self, folder: str, absent: str) -> Path:
        """A listed folder whose every file matches the manifest; `absent` says what it means when none is."""
        listed = [r for r in self.files if r.startswith(folder + "/")]
        if not listed:
            raise CaptureError(f"{self.dir}: {absent}")
        for rel in listed:
            self._checked(rel)
        return self._path(folder)

    def verify(self) -> list[str]:
        """Listed files whose checksum does not match (empty when all verify), checked by VERIFIERS threads (sha256
        and file reads release the GIL; a paper-rig capture is 14 GB, 43 GB with its raw frames)."""
        rels = list(self.files)
        with ThreadPoolExecutor(VERIFIERS) as pool:
            return [rel for rel, ok in zip(rels, pool.map(self.verified, rels)) if not ok]

    def complete(self, verify: bool = True) -> bool:
        """Every photo of the plan is listed and (verify) every listed file verifies: a finished capture."""
        plan = self.header.get("plan", [])
        listed = bool(plan) and all(photo_stem(p["index"], p["camera_index"]) in self.photos for p in plan)
        return listed and not (verify and self.verify())

    def holds(self, header: dict) -> bool:
        """True when this folder's capture is the one `header` describes (twin.capture.runner.capture_header)."""
        return not _differing(self.header, header)

    def photo(self, index: int, camera_index: int) -> np.ndarray:
        """(H, W, 3) float32 HDR photo k of camera c, checked against the manifest and for finite values."""
        from twin.materials.exr import read_rgb_exr

        path = self._checked(_photo_file(index, camera_index))
        img = read_rgb_exr(path)
        if not np.all(np.isfinite(img)):
            raise CaptureError(f"{path}: the photo holds NaN or Inf values")
        return img

    def raw_frames(self, index: int, camera_index: int) -> list[np.ndarray]:
        """The (H, W) uint16 raw frames of photo k of camera c, in bracket order."""
        from twin.camera.bayer import unpack_bayer_rg12p

        if not self.keeps_raw_frames:
            raise CaptureError(f"{self.dir}: the capture was made without raw frames; capture again with --raw (the "
                               "same seed gives the same frames)")
        rec = self.photos.get(photo_stem(index, camera_index))
        if rec is None:
            raise CaptureError(f"{self.dir}: photo {photo_stem(index, camera_index)} was not taken")
        h, w = rec["raw_shape"]
        return [unpack_bayer_rg12p(self._checked(_raw_file(index, camera_index, j)).read_bytes(), h, w)
                for j in range(len(rec["exposures_s"]))]

    def patterns(self):
        """The patterns the LEDs showed (a twin.capture.patterns.PatternSet)."""
        from twin.capture.patterns import load_patterns

        return load_patterns(self._checked(PATTERNS))

    def rig(self):
        """The rig the capture was made with (its rig/ folder), checked against the manifest's digest."""
        from twin.rig.format import load_rig_dir

        rig = load_rig_dir(self._checked_folder(RIG, "the capture carries no rig folder"))
        if rig.digest() != self.rig_digest:
            raise CaptureError(f"{self.dir / RIG}: its digest differs from the manifest's rig_digest")
        return rig

    @property
    def has_ground_truth(self) -> bool:
        return any(r.startswith(MAPS + "/") for r in self.files)

    def ground_truth_maps(self):
        """The sample's true SVBRDF maps (a twin capture only)."""
        from twin.materials.samples import read_maps

        return read_maps(self._checked_folder(MAPS, "no ground truth (a capture of the real device cannot be "
                                                    "scored)"))

    def pixel_texel(self, camera_index: int) -> np.ndarray:
        """(H, W, 2) float32: the true texel (row, col) each pixel of camera c sees, NaN off the sample."""
        return np.load(self._checked(_pixel_texel_file(camera_index)), allow_pickle=False)

    # --- writing --------------------------------------------------------------------------------------
    @classmethod
    def create(cls, directory, header: dict, break_lock: bool = False) -> "CaptureSession":
        """Start or resume the capture `header` describes in `directory`, holding its lock until `close`
        (`break_lock`: take a lock that another host recorded, twin.lock)."""
        d = Path(directory)
        created = not d.exists()
        files, photos = {}, {}
        if (d / MANIFEST).exists():
            old = _read_manifest(d)
            mismatch = _differing(old, header)
            if "raw_frames" in mismatch:  # the one option a user is likely to forget on a resume: name it
                kept = "with" if _keeps_raw_frames(old) else "without"
                raise CaptureError(f"{d} holds a different capture ({', '.join(mismatch)} differ: it was made {kept} "
                                   f"--raw); resume it {kept} --raw or choose another folder")
            if mismatch:
                raise CaptureError(f"{d} holds a different capture ({', '.join(mismatch)} differ); "
                                   "choose another folder")
            files, photos = dict(old.get("files", {})), dict(old.get("photos", {}))
        elif d.exists() and any(p.name != LOCK for p in d.iterdir()):
            raise CaptureError(f"{d} exists and is not a capture folder; choose another folder")
        session = cls(d, dict(header), files, photos)
        session._created = created
        try:
            session._lock = FolderLock(d, "another capture").acquire(break_lock)
        except LockError as e:
            raise CaptureError(str(e)) from None
        # a writer killed mid-write leaves its temporary files (never listed in the manifest); the lock is ours, so
        # nobody else is writing them
        remove_leftovers(d)
        if not (d / MANIFEST).exists():
            session.save()  # from here on the folder is a capture folder, resumable whatever is killed next
        return session

    def close(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def discard_if_new(self) -> None:
        """After a failure: remove the folder when this writer created it and took no photo yet."""
        if self._created and not self.photos and self._lock is not None:
            self._lock.remove_folder()
        self.close()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.discard_if_new()
        return False

    def _write(self, rel: str, data: bytes) -> None:
        write_bytes_atomic(self._path(rel), data)
        self.files[rel] = hashlib.sha256(data).hexdigest()

    def _write_with(self, rel: str, writer) -> None:
        """`writer(tmp_path)` writes the file; it is renamed into place and checksummed."""
        path = self._path(rel)
        with atomic_path(path) as tmp:
            writer(tmp)
        self.files[rel] = file_sha256(path)

    def _write_folder(self, folder: str, writer) -> None:
        """`writer(path)` writes a whole folder (unless its listed files all verify), then each file is listed."""
        listed = [r for r in self.files if r.startswith(folder + "/")]
        if listed and all(self.verified(r) for r in listed):
            return
        for r in listed:
            del self.files[r]
        path = self._path(folder)
        if path.exists():
            shutil.rmtree(path)
        writer(path)
        for f in sorted(path.iterdir()):
            self.files[f"{folder}/{f.name}"] = file_sha256(f)

    def write_setup(self, patterns, rig, maps) -> None:
        """The files every capture starts with: the patterns, the rig folder and (a twin capture) the true maps."""
        from twin.materials.samples import write_maps
        from twin.rig.format import save_rig

        if not self.verified(PATTERNS):
            self._write(PATTERNS, patterns.to_bytes())
        self._write_folder(RIG, lambda d: save_rig(rig, d, overwrite=True))
        if maps is not None:
            self._write_folder(MAPS, lambda d: write_maps(maps, d))
        self.save()

    def pixel_texel_done(self, camera_index: int) -> bool:
        return self.verified(_pixel_texel_file(camera_index))

    def write_pixel_texel(self, camera_index: int, pixel_texel: np.ndarray) -> None:
        self._write_with(_pixel_texel_file(camera_index),
                         lambda tmp: np.save(tmp, np.asarray(pixel_texel, np.float32)))
        self.save()

    def photo_done(self, photo: Photo) -> bool:
        rec = self.photos.get(photo_stem(photo.index, photo.camera_index))
        return rec is not None and all(self.verified(r) for r in rec["files"])

    def write_photo(self, photo: Photo, raws: list[np.ndarray] | None, radiance: np.ndarray, record: dict) -> None:
        """One photo: its raw frames `raws` (BayerRG12p; only where the capture keeps them, keeps_raw_frames: None
        may be passed otherwise), the merged HDR EXR, then its manifest record, whose raw_shape is the photo's pixel
        grid (the frames' too: the merge demosaics them to it). Thread-safe: photos may be written concurrently
        (each lists itself in the manifest once its files are complete)."""
        from twin.camera.bayer import pack_bayer_rg12p
        from twin.materials.exr import write_rgb_exr

        i, c = photo.index, photo.camera_index
        done = {}
        # not fsynced (twin.atomic, durable=False): a resumed capture verifies a photo's files before it counts as
        # taken (photo_done), and syncing the paper rig's 196 photos (14 GB, 43 GB with raw frames) adds about a
        # sixth to a 1024^2 capture's time (docs/performance.md); the manifest that lists them is fsynced
        for j, raw in enumerate(raws if self.keeps_raw_frames else ()):
            data = pack_bayer_rg12p(raw)
            write_bytes_atomic(self._path(_raw_file(i, c, j)), data, durable=False)
            done[_raw_file(i, c, j)] = hashlib.sha256(data).hexdigest()
        path = self._path(_photo_file(i, c))
        # uncompressed: zip saves nothing on a noisy float32 photo (73.2 against 73.7 MB at 2664 x 2304) and costs
        # several times the write time and twice the read time (docs/performance.md, the capture with files written)
        write_rgb_exr(path, radiance, compression="none", durable=False)
        done[_photo_file(i, c)] = file_sha256(path)
        with self._mutex:
            self.files.update(done)
            self.photos[photo_stem(i, c)] = {**record, "raw_shape": list(radiance.shape[:2]), "files": list(done)}
            self.save()

    def save(self) -> None:
        doc = {**self.header, **dict(zip(BODY, (self.photos, self.files)))}
        write_bytes_atomic(self._path(MANIFEST), json.dumps(doc, sort_keys=True, separators=(",", ":")).encode())


def verify(directory) -> list[str]:
    """Files of a capture folder whose checksum does not match its manifest (empty when all verify)."""
    return CaptureSession.open(directory).verify()

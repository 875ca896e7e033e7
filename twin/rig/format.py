"""The rig folder format: `rig.toml` (scalars, cameras) + `leds.npz` and `frame.npz` (arrays).

    RIG_DIR/rig.toml    format = "hemicube-rig", version, name, length_unit, led_profile, notes,
                        [sample], [frame], [bottom], [[boards]], [[cameras]] (+ [cameras.sensor])
    RIG_DIR/leds.npz    the per-LED arrays of twin.rig.model.LEDs
    RIG_DIR/frame.npz   marker_ids, marker_corners (only when the rig has a holder frame)
    RIG_DIR/flat_field.npz  per camera name, its (H, W) float32 falloff beyond the radial model (only when
                        calibrated: calibration.vignetting)

Loading validates everything (twin.rig.model.validate) and never unpickles: npz files are opened with
allow_pickle=False. Floats are written with repr() in TOML and in their own dtype in npz, so
save -> load round-trips bit-exactly. Files may declare length_unit = "m"; lengths are converted to mm
on load (twin.rig.units). Saving is atomic: the folder is assembled beside the target and renamed into place.
"""
from __future__ import annotations

import io
import os
import tomllib
from pathlib import Path

import numpy as np
import tomli_w

from twin.atomic import atomic_folder
from twin.outputs import Kind
from twin.rig.camera import Camera, SensorParams
from twin.rig.model import (FORMAT_NAME, RIG_FORMAT_VERSION, Board, BottomBoard, HolderFrame, LEDs, Rig, RigError,
                            SamplePlane, rig_to_toml_dict)
from twin.rig.units import MM_PER, to_mm

RIG_FOLDER = Kind("a rig folder", ("rig.toml",))  # what `rig export --force` replaces (twin.outputs)

LENGTH_FIELDS = {  # what scales with the length unit
    "sample": ("origin", "max_size"),
    "frame": ("inner_size", "outer_size", "height", "marker_size"),
    "bottom": ("acrylic_thickness",),
}


# --- writing -----------------------------------------------------------------------------------------
def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _files(rig: Rig) -> dict[str, bytes]:
    files = {"rig.toml": tomli_w.dumps(rig_to_toml_dict(rig)).encode(),
             "leds.npz": _npz_bytes({k: getattr(rig.leds, k) for k in LEDs.ARRAYS})}
    if rig.frame is not None:
        files["frame.npz"] = _npz_bytes({"marker_ids": rig.frame.marker_ids,
                                         "marker_corners": rig.frame.marker_corners})
    if rig.flat_fields:
        files["flat_field.npz"] = _npz_bytes(dict(rig.flat_fields))
    return files


def save_rig(rig: Rig, directory: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write `rig` as a rig folder at `directory` (module docstring: positions in mm, the right-handed world of
    twin/rig/units.py) atomically: either the complete new folder is there, or the old state; an existing folder is
    replaced only with `overwrite`. Returns its path."""
    with atomic_folder(directory, overwrite) as tmp:
        for name, data in _files(rig).items():
            (tmp / name).write_bytes(data)
    return Path(directory)


# --- reading -----------------------------------------------------------------------------------------
def load_rig_dir(directory: str | os.PathLike) -> Rig:
    d = Path(directory)
    if not d.is_dir():
        raise RigError(f"{d}: not a rig folder (no such directory)")
    toml_path = d / "rig.toml"
    if not toml_path.is_file():
        raise RigError(f"{d}: missing rig.toml")
    try:
        doc = tomllib.loads(toml_path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise RigError(f"{toml_path}: not valid TOML ({e})") from None
    if doc.get("format") != FORMAT_NAME:
        raise RigError(f"{toml_path}: format must be {FORMAT_NAME!r}, got {doc.get('format')!r}")
    version = doc.get("version")
    if version != RIG_FORMAT_VERSION:
        raise RigError(f"{toml_path}: unknown rig format version {version!r}; this twin reads version "
                       f"{RIG_FORMAT_VERSION}")
    unit = doc.get("length_unit", "mm")
    if unit not in MM_PER:
        raise RigError(f"{toml_path}: length_unit must be one of {sorted(MM_PER)}, got {unit!r}")

    def section(name, required=True):
        s = doc.get(name)
        if s is None:
            if required:
                raise RigError(f"{toml_path}: missing [{name}] table")
            return None
        if not isinstance(s, dict):
            raise RigError(f"{toml_path}: [{name}] must be a table")
        s = dict(s)
        for k in LENGTH_FIELDS.get(name, ()):
            if k in s:
                s[k] = to_mm(np.asarray(s[k], float), unit)
                s[k] = tuple(s[k].tolist()) if s[k].ndim else float(s[k])
        return s

    leds_arrays = _load_npz(d / "leds.npz", tuple(LEDs.ARRAYS))
    leds_arrays["positions"] = to_mm(leds_arrays["positions"].astype(np.float64), unit)
    leds_arrays["diffuser_radius"] = to_mm(leds_arrays["diffuser_radius"], unit)
    try:
        sample = SamplePlane(**section("sample"))
        frame = None
        if (fs := section("frame", required=False)) is not None:
            fa = _load_npz(d / "frame.npz", ("marker_ids", "marker_corners"))
            frame = HolderFrame(**fs, marker_ids=fa["marker_ids"],
                                marker_corners=to_mm(fa["marker_corners"], unit))
        bottom = BottomBoard(**bs) if (bs := section("bottom", required=False)) is not None else None
        boards = [Board(**b) for b in doc.get("boards", [])]
        cameras = {}
        for c in doc.get("cameras", []):
            c = dict(c)
            sensor = c.pop("sensor", {})
            sensor = SensorParams(**{**sensor, "vignetting": tuple(sensor.get("vignetting", (0, 0, 0))),
                                     "crosstalk": tuple(map(tuple, sensor.get("crosstalk", np.eye(3))))})
            c["t"] = to_mm(np.asarray(c["t"], float), unit)
            if c["name"] in cameras:
                raise RigError(f"{toml_path}: two cameras are named {c['name']!r}")
            cameras[c["name"]] = Camera(**c, sensor=sensor)
        flat_fields = {}
        if (d / "flat_field.npz").is_file():
            flat_fields = _load_npz(d / "flat_field.npz", tuple(_npz_keys(d / "flat_field.npz")))
        return Rig(name=doc.get("name", d.name), leds=LEDs(**leds_arrays), boards=boards, cameras=cameras,
                   sample=sample, frame=frame, bottom=bottom, led_profile=doc.get("led_profile", "cosine"),
                   notes=doc.get("notes", ""), flat_fields=flat_fields)
    except RigError as e:
        raise RigError(f"{d}: {e}") from None
    except (TypeError, KeyError, ValueError) as e:
        raise RigError(f"{d}: malformed rig description ({type(e).__name__}: {e})") from None


def _npz_keys(path: Path) -> list[str]:
    try:
        with np.load(path, allow_pickle=False) as z:
            return list(z.files)
    except (OSError, ValueError, AttributeError) as e:
        raise RigError(f"{path}: not a readable npz archive ({type(e).__name__}: {e})") from None


def _load_npz(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise RigError(f"{path.parent}: missing {path.name}")
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise RigError(f"{path}: not an npz archive (a single .npy array)")
        with z:
            missing = [k for k in keys if k not in z.files]
            if missing:
                raise RigError(f"{path}: missing array(s) {missing}")
            return {k: z[k] for k in keys}
    except RigError:
        raise
    except ValueError as e:  # object arrays need pickle: refused
        raise RigError(f"{path}: refused to read ({e}); rig files never contain pickled objects") from None
    except (OSError, EOFError) as e:
        raise RigError(f"{path}: not a readable npz file ({e})") from None

"""The rig model: an immutable, validated description of the light-hemicube.

Everything downstream (kernels, virtual capture, network, calibration, real backends, views) reads this.
Units and frames are those of `twin.rig.units` (millimetres, right-handed, +z out of the sample, OpenCV
cameras). LED index order follows the released `lights.bin` for the 12,288 upper LEDs
(l = 1024*tile + 32*slow + fast, reference §1.3) so that pattern files and lumitexels are
interchangeable with the reference; bottom LEDs, when present, follow them.
"""
from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field, fields, replace
from types import MappingProxyType
from typing import Mapping

import numpy as np
import tomli_w

from twin.rig.camera import Camera, SensorParams
from twin.rig.cross import CROSS_SHAPE

RIG_FORMAT_VERSION = 1
LED_PROFILES = ("cosine", "polynomial")
PROFILE_PARAMS = 8  # reference §1.1: lights_angular.npy holds 8 parameters per LED


class RigError(ValueError):
    """A rig description is invalid or cannot be read. The message says what and where."""


def _frozen(a, dtype):
    a = np.array(a, dtype=dtype)  # always a copy: the rig owns its arrays
    a.flags.writeable = False
    return a


@dataclass(frozen=True)
class Board:
    """One LED board: a rows x cols grid on one face of the cube."""

    name: str
    face: str  # "-x", "+x", "-y", "+y", "top", "bottom"
    rows: int
    cols: int


@dataclass(frozen=True)
class LEDs:
    """Per-LED arrays, all of length L.

    positions   (L, 3) mm, world frame
    normals     (L, 3) unit emission normals, pointing into the cube
    board       (L,)   index into Rig.boards
    row, col    (L,)   position on the board
    intensity   (L, 3) relative RGB radiant intensity at full drive (W/sr in the physical convention)
    profile     (L, 8) angular-profile parameters Psi (meaning set by Rig.led_profile, see twin.optics.emitter)
    diffuser_radius (L,) mm, radius of the LED's diffuser disc (LEDs are point emitters in the kernels:
                at >= 300 mm a <= 5 mm disc changes the inverse-square term by < (5/300)^2 = 3e-4)
    is_bottom   (L,)   True for the LEDs under the translucent acrylic board
    cross_pixel (L, 2) (col, row) in the unfolded-cube image (twin.rig.cross)
    """

    positions: np.ndarray
    normals: np.ndarray
    board: np.ndarray
    row: np.ndarray
    col: np.ndarray
    intensity: np.ndarray
    profile: np.ndarray
    diffuser_radius: np.ndarray
    is_bottom: np.ndarray
    cross_pixel: np.ndarray

    ARRAYS = {
        "positions": (np.float64, (3,)),
        "normals": (np.float64, (3,)),
        "board": (np.int16, ()),
        "row": (np.int16, ()),
        "col": (np.int16, ()),
        "intensity": (np.float32, (3,)),
        "profile": (np.float32, (PROFILE_PARAMS,)),
        "diffuser_radius": (np.float32, ()),
        "is_bottom": (np.bool_, ()),
        "cross_pixel": (np.int16, (2,)),
    }

    def __post_init__(self):
        n = None
        for name, (dtype, tail) in self.ARRAYS.items():
            a = np.asarray(getattr(self, name))
            if a.ndim != 1 + len(tail) or a.shape[1:] != tail:
                raise RigError(f"leds.{name}: expected shape (L, {', '.join(map(str, tail))}) "
                               .replace(", )", ")") + f"got {a.shape}")
            if n is None:
                n = a.shape[0]
            elif a.shape[0] != n:
                raise RigError(f"leds.{name}: has {a.shape[0]} entries but leds.positions has {n}")
            if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                bad = np.flatnonzero(~np.all(np.isfinite(a.reshape(n, -1)), axis=1))
                raise RigError(f"leds.{name}: NaN or Inf at LED(s) {bad[:5].tolist()}")
            if a.dtype.kind in "iu" and np.issubdtype(dtype, np.integer):
                info = np.iinfo(dtype)
                if a.size and (a.min() < info.min or a.max() > info.max):
                    raise RigError(f"leds.{name}: values out of range for {np.dtype(dtype).name}")
            object.__setattr__(self, name, _frozen(a, dtype))

    def __len__(self):
        return self.positions.shape[0]

    def subset(self, index) -> "LEDs":
        return LEDs(**{k: getattr(self, k)[index] for k in self.ARRAYS})


@dataclass(frozen=True)
class SamplePlane:
    """The sample plane: a square of up to `max_size` mm centred on `origin`, lying in the plane with
    normal `normal`; `x_axis` is the in-plane direction of texture columns (reference §7.1)."""

    origin: tuple[float, float, float] = (0.0, 0.0, -122.0)
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
    x_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    max_size: float = 150.0

    def __post_init__(self):
        for name in ("origin", "normal", "x_axis"):
            v = np.asarray(getattr(self, name), float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise RigError(f"sample.{name}: expected 3 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, tuple(float(x) for x in v))
        for name in ("normal", "x_axis"):
            if abs(np.linalg.norm(getattr(self, name)) - 1) > 1e-6:
                raise RigError(f"sample.{name} must be a unit vector, got {getattr(self, name)}")
        if abs(np.dot(self.normal, self.x_axis)) > 1e-6:
            raise RigError("sample.x_axis must be orthogonal to sample.normal")
        if not (np.isfinite(self.max_size) and self.max_size > 0):
            raise RigError(f"sample.max_size must be positive, got {self.max_size}")

    @property
    def y_axis(self) -> np.ndarray:
        return np.cross(self.normal, self.x_axis)

    def corners(self, size: float | None = None) -> np.ndarray:
        """(4, 3) corners of the centred square of side `size` (default max_size)."""
        h = 0.5 * (self.max_size if size is None else size)
        o, x, y = np.asarray(self.origin), np.asarray(self.x_axis), self.y_axis
        return np.array([o - h * x - h * y, o + h * x - h * y, o + h * x + h * y, o - h * x + h * y])


@dataclass(frozen=True)
class HolderFrame:
    """The aluminium frame that holds the sample, with fiducial markers on its top face (paper §5,
    "aluminium frame with ARTags"). A square ring in the sample plane: inner and outer side lengths,
    height above the plane. Markers are squares of side `marker_size` with OpenCV ArUco ids; their
    corners (M, 4, 3) are in world mm, in ArUco corner order (top-left, top-right, bottom-right,
    bottom-left as seen from above, +x right, +y up)."""

    inner_size: float = 150.0
    outer_size: float = 210.0
    height: float = 1.5
    marker_dictionary: str = "DICT_6X6_250"
    marker_size: float = 20.0
    marker_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    marker_corners: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 3)))

    def __post_init__(self):
        for name in ("inner_size", "outer_size", "height", "marker_size"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise RigError(f"frame.{name} must be positive, got {v}")
        if self.outer_size <= self.inner_size:
            raise RigError("frame.outer_size must exceed frame.inner_size")
        ids = np.asarray(self.marker_ids)
        corners = np.asarray(self.marker_corners, float)
        if ids.ndim != 1 or corners.shape != (len(ids), 4, 3):
            raise RigError(f"frame markers: ids {ids.shape} and corners {corners.shape} must be (M,) and (M, 4, 3)")
        if not np.all(np.isfinite(corners)):
            raise RigError("frame.marker_corners: NaN or Inf")
        if len(np.unique(ids)) != len(ids):
            raise RigError("frame.marker_ids: duplicate marker ids")
        object.__setattr__(self, "marker_ids", _frozen(ids, np.int32))
        object.__setattr__(self, "marker_corners", _frozen(corners, np.float64))

    def mesh(self, sample: SamplePlane) -> tuple[np.ndarray, np.ndarray]:
        """Triangle mesh (vertices (V,3) mm, faces (F,3)) of the frame: four boxes around the sample."""
        a, b, h = self.inner_size / 2, self.outer_size / 2, self.height
        boxes = [(-b, -b, b, -a), (-b, a, b, b), (-b, -a, -a, a), (a, -a, b, a)]  # (x0, y0, x1, y1)
        o, x, y, n = (np.asarray(sample.origin), np.asarray(sample.x_axis), sample.y_axis,
                      np.asarray(sample.normal))
        # unit-cube corners and its 12 outward-wound triangles
        cube = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], float)
        tris = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                         [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
        verts, faces = [], []
        for k, (x0, y0, x1, y1) in enumerate(boxes):
            c = cube * [x1 - x0, y1 - y0, h] + [x0, y0, 0.0]
            verts.append(o + c[:, :1] * x + c[:, 1:2] * y + c[:, 2:] * n)
            faces.append(tris + 8 * k)
        return np.concatenate(verts), np.concatenate(faces).astype(np.int32)


@dataclass(frozen=True)
class BottomBoard:
    """The bottom LED board under the translucent acrylic board the sample rests on (paper §5).
    `acrylic_transmission` is the fraction of light the diffusing acrylic passes (diffuse, Lambertian
    transmission in the forward model)."""

    acrylic_thickness: float = 5.0
    acrylic_transmission: float = 0.85

    def __post_init__(self):
        if not (np.isfinite(self.acrylic_thickness) and self.acrylic_thickness >= 0):
            raise RigError(f"bottom.acrylic_thickness must be >= 0, got {self.acrylic_thickness}")
        if not (0 <= self.acrylic_transmission <= 1):
            raise RigError(f"bottom.acrylic_transmission must lie in [0, 1], got {self.acrylic_transmission}")


@dataclass(frozen=True)
class Rig:
    """The whole device. Build it with the constructor (it validates), `twin.load_rig`, or the
    builders in `twin.rig.builtin`. Lengths in mm, in the right-handed world frame of twin.rig.units (+z out of
    the sample).

    leds        the L LEDs' arrays (LEDs): positions (L, 3) mm, unit normals (L, 3), intensity (L, 3), profile (L, 8)
    boards      the LED boards (rows x cols grids), indexed by leds.board
    cameras     name -> Camera: K (3, 3) and resolution in pixels, dist (5,), pose R (3, 3) | t (3,) mm (OpenCV)
    sample      the sample plane: origin (mm), normal, x_axis, max_size (mm)
    frame, bottom   the holder frame and the bottom board under the acrylic, or None
    led_profile the meaning of leds.profile ("cosine" or "polynomial": twin.optics.emitter)
    flat_fields name -> (H, W) float32 falloff beyond the camera's radial vignetting (a calibrated flat field)
    """

    name: str
    leds: LEDs
    boards: tuple[Board, ...]
    cameras: Mapping[str, Camera]
    sample: SamplePlane = field(default_factory=SamplePlane)
    frame: HolderFrame | None = None
    bottom: BottomBoard | None = None
    led_profile: str = "cosine"
    notes: str = ""
    length_unit: str = "mm"
    # per camera, an (H, W) float32 light-falloff factor beyond the camera's radial vignetting model (a
    # calibrated flat field: the hood's corners, dust; calibration.vignetting). Cameras without one: radial only
    flat_fields: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "boards", tuple(self.boards))
        object.__setattr__(self, "cameras", MappingProxyType(dict(self.cameras)))
        maps = {k: np.array(v, dtype=np.float32) for k, v in dict(self.flat_fields).items()}
        for a in maps.values():
            a.flags.writeable = False
        object.__setattr__(self, "flat_fields", MappingProxyType(maps))
        validate(self)

    # --- the public API names (kept stable; the other packages, external code and tests use them) -
    @property
    def led_positions(self) -> np.ndarray:
        return self.leds.positions

    @property
    def led_normals(self) -> np.ndarray:
        return self.leds.normals

    @property
    def is_bottom(self) -> np.ndarray:
        return self.leds.is_bottom

    @property
    def num_leds(self) -> int:
        return len(self.leds)

    def face_leds(self) -> dict[str, np.ndarray]:
        """Each face of the cube (Board.face: "-x", "+x", "-y", "+y", "top", "bottom") -> the indices of its boards'
        LEDs, for the faces that have any, in board order."""
        faces: dict[str, list[int]] = {}
        for b, board in enumerate(self.boards):
            faces.setdefault(board.face, []).append(b)
        sel = {face: np.flatnonzero(np.isin(self.leds.board, boards)) for face, boards in faces.items()}
        return {face: idx for face, idx in sel.items() if idx.size}

    @property
    def primary(self) -> Camera:
        """The first camera (the 90 deg view in the built-in rigs)."""
        return next(iter(self.cameras.values()))

    def camera(self, name: str | None = None) -> Camera:
        if name is None:
            return self.primary
        try:
            return self.cameras[name]
        except KeyError:
            raise KeyError(f"rig {self.name!r} has no camera {name!r}; it has {list(self.cameras)}") from None

    def digest(self) -> str:
        """sha256 of the rig's canonical serialisation (used in capture manifests and as a cache key)."""
        if "_digest" not in self.__dict__:  # immutable, so computed once; bypasses the frozen __setattr__
            self.__dict__["_digest"] = hashlib.sha256(canonical_bytes(self)).hexdigest()
        return self.__dict__["_digest"]

    def geometry_digest(self) -> str:
        """sha256 of the rig without how its cameras record light (their sensors: noise, vignetting, crosstalk;
        the per-pixel flat fields), i.e. of what an acquisition network and its patterns depend on: the LEDs,
        their profile, the boards, the sample plane, the cameras' poses and lenses. A calibration of the
        former keeps it."""
        return self._without_sensors().digest()

    def layout_digest(self) -> str:
        """sha256 of the rig without what a lab calibrates of a device: how the cameras record light
        (geometry_digest), the cameras' lenses and poses (calibration.cameras) and the LEDs' positions, normals,
        profiles and intensities (calibration.leds). Two rigs with the same layout digest are one device,
        calibrated differently: the same LEDs on the same boards, the same sample plane and frame, the same
        cameras (names and pixel grids)."""
        return hashlib.sha256(canonical_bytes(self._without_sensors(), ("positions", "normals", "profile", "intensity"),
                                              without_camera_geometry=True)).hexdigest()

    def _without_sensors(self) -> "Rig":
        """The rig with default camera sensors and no flat fields: without how its cameras record light."""
        return replace(self, cameras={n: replace(c, sensor=SensorParams()) for n, c in self.cameras.items()},
                       flat_fields={})

    def summary(self) -> dict:
        """What `hemicube rig info` prints."""
        per_board = np.bincount(self.leds.board, minlength=len(self.boards))
        pos = self.leds.positions
        return {
            "name": self.name,
            "length_unit": self.length_unit,
            "num_leds": self.num_leds,
            "num_upper_leds": int((~self.is_bottom).sum()),
            "num_bottom_leds": int(self.is_bottom.sum()),
            "boards": [{"name": b.name, "face": b.face, "grid": [b.rows, b.cols], "leds": int(c)}
                       for b, c in zip(self.boards, per_board)],
            "bounding_box": {"min": pos.min(0).round(3).tolist(), "max": pos.max(0).round(3).tolist()},
            "led_profile": self.led_profile,
            "sample": {"origin": list(self.sample.origin), "normal": list(self.sample.normal),
                       "max_size": self.sample.max_size},
            "cameras": {n: {"centre": c.centre.round(4).tolist(), "resolution": [c.width, c.height],
                            "fx": c.K[0, 0], "fy": c.K[1, 1], "cx": c.K[0, 2], "cy": c.K[1, 2],
                            "dist": c.dist.tolist(), "assumed": c.assumed}
                        for n, c in self.cameras.items()},
            "digest": self.digest(),
        }


# ---------------------------------------------------------------------------------------------------
def validate(rig: Rig) -> None:
    """Raise RigError with a precise message for anything physically or structurally wrong."""
    leds = rig.leds
    L = len(leds)
    if rig.length_unit != "mm":
        raise RigError(f"in-memory rigs are in mm (twin.rig.units); got length_unit={rig.length_unit!r}")
    if rig.led_profile not in LED_PROFILES:
        raise RigError(f"led_profile {rig.led_profile!r} unknown; expected one of {LED_PROFILES}")
    if L == 0:
        raise RigError("the rig has no LEDs")
    if not rig.cameras:
        raise RigError("the rig has no cameras")
    for name, ff in rig.flat_fields.items():
        if name not in rig.cameras:
            raise RigError(f"flat field for camera {name!r}, which the rig does not have ({list(rig.cameras)})")
        c = rig.cameras[name]
        if ff.shape != (c.height, c.width):
            raise RigError(f"flat field of camera {name!r} is {ff.shape}, the camera is ({c.height}, {c.width})")
        if not np.all(np.isfinite(ff)) or ff.min() <= 1e-3 or ff.max() > 2:
            raise RigError(f"flat field of camera {name!r} must be finite and within (0.001, 2]: a falloff factor")
    if leds.board.min() < 0 or leds.board.max() >= len(rig.boards):
        raise RigError(f"leds.board refers to boards outside 0..{len(rig.boards) - 1}")
    for b, board in enumerate(rig.boards):
        sel = leds.board == b
        if np.any((leds.row[sel] < 0) | (leds.row[sel] >= board.rows) | (leds.col[sel] < 0)
                  | (leds.col[sel] >= board.cols)):
            raise RigError(f"board {board.name!r}: LED (row, col) outside its {board.rows}x{board.cols} grid")
        if sel.any() and len(np.unique(leds.is_bottom[sel])) > 1:
            raise RigError(f"board {board.name!r} mixes upper and bottom LEDs")
    key = (leds.board.astype(np.int64) << 32) | (leds.row.astype(np.int64) << 16) | leds.col.astype(np.int64)
    if len(np.unique(key)) != L:
        raise RigError("two LEDs share the same (board, row, col)")
    if leds.is_bottom.any() and rig.bottom is None:
        raise RigError("the rig has bottom LEDs but no [bottom] board description")

    norms = np.linalg.norm(leds.normals, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1) > 1e-4)
    if bad.size:
        raise RigError(f"leds.normals must be unit vectors: LED {bad[0]} has length {norms[bad[0]]:.6f} "
                       f"({bad.size} LED(s) affected)")
    to_sample = np.asarray(rig.sample.origin) - leds.positions
    facing = np.einsum("ij,ij->i", leds.normals, to_sample)
    bad = np.flatnonzero(facing <= 0)
    if bad.size:
        raise RigError(f"LED {bad[0]} points away from the sample (normal {leds.normals[bad[0]].round(3)} at "
                       f"{leds.positions[bad[0]].round(1)} mm); normals must point into the cube "
                       f"({bad.size} LED(s) affected; released files store them outward)")
    _check_duplicates(leds.positions)
    if np.any(leds.intensity < 0):
        raise RigError("leds.intensity must be >= 0")
    if np.any(leds.diffuser_radius < 0):
        raise RigError("leds.diffuser_radius must be >= 0")

    cp = leds.cross_pixel.astype(np.int64)
    H, W = CROSS_SHAPE
    if np.any((cp[:, 0] < 0) | (cp[:, 0] >= W) | (cp[:, 1] < 0) | (cp[:, 1] >= H)):
        raise RigError(f"leds.cross_pixel outside the {W}x{H} unfolded-cube image")
    if len(np.unique(cp[:, 1] * W + cp[:, 0])) != L:
        raise RigError("two LEDs share one pixel of the unfolded-cube image")

    for name, cam in rig.cameras.items():
        _check_camera(name, cam, rig.sample)


def _check_duplicates(positions: np.ndarray, tol: float = 1.0) -> None:
    from scipy.spatial import cKDTree

    pairs = cKDTree(positions).query_pairs(tol, output_type="ndarray")
    if len(pairs):
        i, j = pairs[0]
        raise RigError(f"duplicate LEDs: LED {i} and LED {j} are closer than {tol} mm "
                       f"({positions[i].round(2)} vs {positions[j].round(2)}); {len(pairs)} pair(s)")


def _check_camera(name: str, cam: Camera, sample: SamplePlane) -> None:
    for attr, shape in (("K", (3, 3)), ("dist", (5,)), ("R", (3, 3)), ("t", (3,))):
        a = getattr(cam, attr)
        if a.shape != shape:
            raise RigError(f"camera {name!r}: {attr} must have shape {shape}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise RigError(f"camera {name!r}: {attr} contains NaN or Inf")
    if cam.width <= 0 or cam.height <= 0:
        raise RigError(f"camera {name!r}: resolution must be positive, got {cam.width}x{cam.height}")
    if not np.allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-5) or np.linalg.det(cam.R) < 0:
        raise RigError(f"camera {name!r}: R is not a rotation (orthonormal, det +1)")
    if cam.K[0, 0] <= 0 or cam.K[1, 1] <= 0 or cam.K[2, 2] != 1 or np.any(cam.K[1:, 0] != 0) or cam.K[2, 1] != 0:
        raise RigError(f"camera {name!r}: K must be upper-triangular with positive focal lengths and K[2,2] = 1")
    # The centred max-size square must be fully visible: in front of the camera and inside the image.
    uv, z = cam.project(sample.corners())
    if np.any(z <= 0):
        raise RigError(f"camera {name!r} cannot see the sample: the sample plane is behind it")
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= cam.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= cam.height - 0.5)
    if not inside.all():
        raise RigError(f"camera {name!r} cannot see the whole {sample.max_size:g} mm sample: corners project "
                       f"to {uv.round(1).tolist()} in a {cam.width}x{cam.height} image")


# --- canonical serialisation: the rig.toml document and the digest (twin.rig.format writes the files) ---
FORMAT_NAME = "hemicube-rig"


def rig_to_toml_dict(rig: Rig) -> dict:
    doc = {
        "format": FORMAT_NAME,
        "version": RIG_FORMAT_VERSION,
        "name": rig.name,
        "length_unit": rig.length_unit,
        "led_profile": rig.led_profile,
        "notes": rig.notes,
        "sample": {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(rig.sample).items()},
        "boards": [asdict(b) for b in rig.boards],
        "cameras": [_camera_dict(c) for c in rig.cameras.values()],
    }
    if rig.frame is not None:
        doc["frame"] = {f.name: getattr(rig.frame, f.name) for f in fields(rig.frame)
                        if f.name not in ("marker_ids", "marker_corners")}
    if rig.bottom is not None:
        doc["bottom"] = asdict(rig.bottom)
    return doc


def _camera_dict(c: Camera) -> dict:
    sensor = asdict(c.sensor)
    sensor["vignetting"] = list(sensor["vignetting"])
    sensor["crosstalk"] = [list(r) for r in sensor["crosstalk"]]
    return {"name": c.name, "width": c.width, "height": c.height, "K": c.K.tolist(), "dist": c.dist.tolist(),
            "R": c.R.tolist(), "t": c.t.tolist(), "assumed": c.assumed, "note": c.note, "sensor": sensor}


def canonical_bytes(rig: Rig, without_leds: tuple = (), without_camera_geometry: bool = False) -> bytes:
    """A canonical serialisation for hashing: the TOML text and every array's dtype, shape and bytes (but the
    LED arrays named in `without_leds`, and with without_camera_geometry the cameras' lenses and poses)."""
    doc = rig_to_toml_dict(rig)
    if without_camera_geometry:
        doc["cameras"] = [{k: v for k, v in c.items() if k not in ("K", "dist", "R", "t", "assumed", "note")}
                          for c in doc["cameras"]]
    parts = [tomli_w.dumps(doc).encode()]
    arrays = {f"leds.{k}": getattr(rig.leds, k) for k in LEDs.ARRAYS if k not in without_leds}
    if rig.frame is not None:
        arrays |= {"frame.marker_ids": rig.frame.marker_ids, "frame.marker_corners": rig.frame.marker_corners}
    arrays |= {f"flat_field.{k}": v for k, v in rig.flat_fields.items()}  # none: the digest of a rig before them
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        parts.append(f"{k}:{a.dtype.str}:{a.shape}".encode() + a.tobytes())
    return b"\0".join(parts)

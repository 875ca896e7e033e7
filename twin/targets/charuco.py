"""A ChArUco board (a chessboard whose white squares hold ArUco markers; OpenCV's aruco module) as the twin sees
it: a flat Lambertian print at a pose in the world frame, photographed through a rig camera.

    target = CharucoTarget()                                  # 11 x 8 squares of 15 mm, 5x5 markers
    img = target.photo(camera, R, t, rng=np.random.default_rng(0))   # uint8 (H, W), the board at X = R b + t

Board frame (OpenCV's): origin at the board's outer corner of its first square, x along the squares' rows, y
along the columns, z = x × y; in mm. A world point on the board is X = R @ (x, y, 0) + t.

Image formation here is simple, and says so: the print's reflectance (white 0.85, black 0.04) under uniform
light, box-filtered over `supersample`² sub-pixel rays per pixel (each undistorted and traced exactly through the
camera model), plus Gaussian noise of `noise` (fraction of white) and 8-bit quantisation. The sensor model of
twin.camera is not applied to the board's photos, and the lens model is the rig's five-coefficient OpenCV
one, which is also what the calibration fits (a richer lens simulation is not built).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

__all__ = ["CharucoTarget", "board_pose_facing", "calibration_poses", "flat_pose"]

WHITE, BLACK, BACKGROUND = 0.85, 0.04, 0.12  # reflectances: print paper, printed ink, the rig's floor


@dataclass(frozen=True)
class CharucoTarget:
    squares_x: int = 11
    squares_y: int = 8
    square_mm: float = 15.0
    marker_mm: float = 11.0
    dictionary: str = "DICT_5X5_250"
    texture_px_per_mm: float = 20.0  # the print's resolution in the render (finer than a camera pixel's ~0.08 mm)

    def __post_init__(self):
        if not (self.squares_x >= 3 and self.squares_y >= 3 and 0 < self.marker_mm < self.square_mm):
            raise ValueError(f"a ChArUco board needs >= 3 x 3 squares and 0 < marker < square, got {self}")

    @property
    def size_mm(self) -> tuple[float, float]:
        return self.squares_x * self.square_mm, self.squares_y * self.square_mm

    def board(self):
        import cv2

        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_mm, self.marker_mm, d)

    def corners_mm(self) -> np.ndarray:
        """(N, 3) the inner chessboard corners in the board frame, in OpenCV's corner-id order."""
        return np.asarray(self.board().getChessboardCorners(), np.float64).reshape(-1, 3)

    # one print per board: every photo of a calibration reuses it (B019: a board is frozen, and few are made)
    @functools.lru_cache(maxsize=4)  # noqa: B019
    def texture(self) -> np.ndarray:
        """The print's reflectance image, row r / column c covering board y / x in mm at texture_px_per_mm
        (read-only: shared between photos)."""
        w, h = (int(round(s * self.texture_px_per_mm)) for s in self.size_mm)
        img = self.board().generateImage((w, h), marginSize=0, borderBits=1)
        tex = BLACK + (WHITE - BLACK) * (img.astype(np.float32) / 255.0)
        tex.flags.writeable = False
        return tex

    def radiance(self, camera, R, t, supersample: int = 2) -> np.ndarray:
        """(H, W) float32 reflectance seen by each pixel (box filter over supersample² rays)."""
        R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
        tex = self.texture()
        n = R[:, 2]
        s = int(supersample)
        out = np.full((camera.height, camera.width), BACKGROUND, np.float64)
        x0, y0, x1, y1 = self._footprint(camera, R, t)
        if x1 <= x0 or y1 <= y0:
            return out.astype(np.float32)
        acc = np.zeros((y1 - y0, x1 - x0), np.float64)
        ys, xs = np.mgrid[y0:y1, x0:x1]
        for j in range(s):
            for i in range(s):
                uv = np.stack([xs.ravel() + (i + 0.5) / s - 0.5, ys.ravel() + (j + 0.5) / s - 0.5], axis=1)
                X = camera.plane_points(uv, t, n)
                b = (X - t) @ R  # board coordinates (x, y, ~0)
                acc += _sample(tex, b[:, 0] * self.texture_px_per_mm - 0.5,
                               b[:, 1] * self.texture_px_per_mm - 0.5).reshape(acc.shape)
        out[y0:y1, x0:x1] = acc / (s * s)
        return out.astype(np.float32)

    def _footprint(self, camera, R, t) -> tuple[int, int, int, int]:
        """The pixel box the board's outline projects into (through the distortion), 3 px of margin: only these
        pixels are traced; the rest see the background."""
        w, h = self.size_mm
        e = np.linspace(0, 1, 65)
        edge = np.concatenate([np.stack([e * w, 0 * e], 1), np.stack([e * w, 0 * e + h], 1),
                               np.stack([0 * e, e * h], 1), np.stack([0 * e + w, e * h], 1)])
        uv, z = camera.project(np.concatenate([edge, np.zeros((len(edge), 1))], 1) @ R.T + t)
        if not (z > 0).all():  # partly behind the camera: trace every pixel
            return 0, 0, camera.width, camera.height
        lo, hi = np.floor(uv.min(0)) - 3, np.ceil(uv.max(0)) + 4
        return (int(np.clip(lo[0], 0, camera.width)), int(np.clip(lo[1], 0, camera.height)),
                int(np.clip(hi[0], 0, camera.width)), int(np.clip(hi[1], 0, camera.height)))

    def photo(self, camera, R, t, rng: np.random.Generator, noise: float = 0.005, supersample: int = 2,
              exposure: float = 1.0) -> np.ndarray:
        """An 8-bit grey photo of the board: white paper at ~85% of full scale times `exposure`."""
        v = self.radiance(camera, R, t, supersample) * exposure + rng.normal(0.0, noise, (camera.height, camera.width))
        return np.clip(np.round(v * 255.0), 0, 255).astype(np.uint8)


def _sample(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup of the print at texture pixel coordinates; BACKGROUND off the board (or behind rays)."""
    h, w = tex.shape
    ok = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    out = np.full(x.shape, BACKGROUND, np.float64)
    x0 = np.clip(np.floor(x[ok]).astype(np.int64), 0, w - 2)
    y0 = np.clip(np.floor(y[ok]).astype(np.int64), 0, h - 2)
    fx, fy = x[ok] - x0, y[ok] - y0
    out[ok] = ((tex[y0, x0] * (1 - fx) + tex[y0, x0 + 1] * fx) * (1 - fy)
               + (tex[y0 + 1, x0] * (1 - fx) + tex[y0 + 1, x0 + 1] * fx) * fy)
    return out


def board_pose_facing(camera, target: CharucoTarget, centre, tilt_deg: float, azimuth_deg: float,
                      spin_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of the board with its centre at the world point `centre`, facing the camera, then tilted by
    `tilt_deg` about an in-plane axis at `azimuth_deg` and spun by `spin_deg` about its normal."""
    centre = np.asarray(centre, np.float64)
    z = camera.centre - centre
    z /= np.linalg.norm(z)  # the board's normal towards the camera ... OpenCV boards face -z: flip below
    x = np.cross(camera.R[1], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    base = np.stack([x, y, z], axis=1)

    def rot(axis, deg):
        a = np.radians(deg)
        axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K

    az = np.radians(azimuth_deg)
    R = base @ rot([np.cos(az), np.sin(az), 0.0], tilt_deg) @ rot([0, 0, 1], spin_deg)
    R = R @ np.diag([1.0, -1.0, -1.0])  # board z away from the camera (the printed side faces it)
    w, h = target.size_mm
    t = centre - R @ np.array([w / 2, h / 2, 0.0])
    return R, t


def calibration_poses(camera, target: CharucoTarget, sample_plane, n: int, seed: int) -> list:
    """n board poses (R, t) for an intrinsics calibration of `camera`, from `seed`: the first faces the camera,
    the others are tilted 25-45 deg about evenly turning axes and spun, centred near the sample plane's origin
    (within +-10 mm across, +-20 mm in depth), as a person waves a board under the camera."""
    rng = np.random.default_rng([int(seed), 17])
    o = np.asarray(sample_plane.origin, np.float64)
    nrm = np.asarray(sample_plane.normal, np.float64)
    poses = []
    for k in range(n):
        c = o + rng.normal(0, 10.0, 3) * (1 - np.abs(nrm)) + nrm * rng.uniform(-20, 20)
        tilt = 0.0 if k == 0 else rng.uniform(25, 45)
        poses.append(board_pose_facing(camera, target, c, tilt, 360.0 * k / max(n - 1, 1), rng.uniform(-20, 20)))
    return poses


def flat_pose(target: CharucoTarget, sample_plane) -> tuple[np.ndarray, np.ndarray]:
    """The board lying on the sample plane, centred on its origin, its x along the plane's x (the holder
    registers it there): the pose a camera's extrinsics are measured against."""
    x = np.asarray(sample_plane.x_axis, np.float64)
    n = np.asarray(sample_plane.normal, np.float64)
    R = np.stack([x, np.cross(-n, x), -n], axis=1)  # board z into the plane: the print faces the cameras
    w, h = target.size_mm
    return R, np.asarray(sample_plane.origin, np.float64) - R @ np.array([w / 2, h / 2, 0.0])

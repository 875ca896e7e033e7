"""The forward model's inputs, shared by the numpy path (twin.optics.forward) and the torch bridge
(twin.optics.torch_ops): the conventions (units and scale), the rig's LED and camera arrays on a device,
the kernels' option struct, and the validated per-point and pattern inputs."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from twin.optics import lumitexel as K
from twin.optics.emitter import PROFILE_COSINE, PROFILE_MODES, led_u_axes
from twin.optics.ggx import brdf_modes, check_material

OPENSVBRDF_RENDER_SCALE = 100.0 * math.pi  # S_render, reference §2.1
OPENSVBRDF_PHOTO_SCALE = OPENSVBRDF_RENDER_SCALE * 3000.0 / math.pi  # 3e5, reference §2.1


@dataclass(frozen=True)
class Convention:
    name: str
    scale: float
    length_scale: float
    r2_eps: float
    min_cos_i: float
    eps: float
    rig_profile: bool  # use the rig's Psi (else Lambertian point emitters)
    rig_intensity: bool
    visibility: bool
    bottom: bool


CONVENTIONS = {
    "physical": Convention("physical", 1.0, 1e-3, 0.0, 0.0, 0.0, True, True, True, True),
    "opensvbrdf": Convention("opensvbrdf", OPENSVBRDF_RENDER_SCALE, 1.0, 1e-6, 1e-6, 1e-6, False, False, False, False),
}


_quieted = False


def _init():
    """Initialise Warp, its start-up banner quieted once (a caller may lower the log level afterwards, e.g.
    to collect module-load timings)."""
    global _quieted
    if not _quieted:
        wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
        _quieted = True
    wp.init()


def check_device(device) -> str:
    """The Warp device a name selects ("cpu", "cuda", "cuda:1"), or a ValueError naming what this machine has:
    checked before any work starts, so that a bad --device costs nothing and leaves nothing behind."""
    _init()
    try:
        return str(wp.get_device(device))
    except (RuntimeError, ValueError, TypeError) as e:
        have = ", ".join(str(d) for d in wp.get_devices())
        raise ValueError(f"unknown device {device!r} ({e}); this machine has: {have}") from None


# --- rig data on a device -------------------------------------------------------------------------
@dataclass(frozen=True)
class RigArrays:
    """The rig's per-LED arrays on one device in one float type, plus its occluder mesh."""

    lpos: wp.array
    lnrm: wp.array
    lu: wp.array
    lint: wp.array
    lint_unit: wp.array
    prof: wp.array
    prof_lambert: wp.array
    lbot: wp.array
    mesh: wp.Mesh | None
    cameras: dict


def _build_rig_arrays(rig, device: str, dtype: str) -> RigArrays:
    vec, scal = (wp.vec3d, wp.float64) if dtype == "float64" else (wp.vec3f, wp.float32)
    npd = np.float64 if dtype == "float64" else np.float32
    L = rig.num_leds

    def v(a):
        return wp.array(np.ascontiguousarray(a, dtype=npd), dtype=vec, device=device)

    prof_lambert = np.zeros((L, rig.leds.profile.shape[1]), npd)
    prof_lambert[:, 0] = 1.0
    mesh = None
    if rig.frame is not None:
        verts, faces = rig.frame.mesh(rig.sample)
        mesh = wp.Mesh(points=wp.array(verts.astype(np.float32), dtype=wp.vec3f, device=device),
                       indices=wp.array(faces.ravel(), dtype=wp.int32, device=device))
    cams = {n: wp.array(c.centre[None].astype(npd), dtype=vec, device=device) for n, c in rig.cameras.items()}
    return RigArrays(v(rig.leds.positions), v(rig.leds.normals), v(led_u_axes(rig)), v(rig.leds.intensity),
                     v(np.ones((L, 3))), wp.array(rig.leds.profile.astype(npd), dtype=scal, device=device),
                     wp.array(prof_lambert, dtype=scal, device=device),
                     wp.array(rig.is_bottom.astype(np.int32), dtype=wp.int32, device=device), mesh, cams)


_RIG_ARRAYS: dict[tuple, RigArrays] = {}


def rig_arrays(rig, device: str, dtype: str = "float32") -> RigArrays:
    """The rig's arrays on `device`, built once per (rig content, device, float type): rigs are
    immutable, so equal rigs share device arrays."""
    _init()
    key = (rig.digest(), str(wp.get_device(device)), dtype)
    if key not in _RIG_ARRAYS:
        _RIG_ARRAYS[key] = _build_rig_arrays(rig, device, dtype)
    return _RIG_ARRAYS[key]


def make_options(rig, arrays: RigArrays, convention: str, g: str, fresnel: str, eta: float,
                 visibility: bool | None) -> K.Options:
    try:
        c = CONVENTIONS[convention]
    except KeyError:
        raise ValueError(f"unknown convention {convention!r}; expected one of {sorted(CONVENTIONS)}") from None
    o = K.Options()
    o.g_mode, o.f_mode, o.eta, _ = brdf_modes(g, fresnel, eta)
    o.profile_mode = PROFILE_MODES[rig.led_profile] if c.rig_profile else PROFILE_COSINE
    o.eps, o.length_scale, o.r2_eps, o.min_cos_i, o.scale = c.eps, c.length_scale, c.r2_eps, c.min_cos_i, c.scale
    o.use_bottom = int(c.bottom and rig.bottom is not None)
    o.acrylic_transmission = rig.bottom.acrylic_transmission if rig.bottom is not None else 0.0
    o.plane_normal = wp.vec3(*rig.sample.normal)
    use_vis = c.visibility if visibility is None else visibility
    o.use_visibility = int(bool(use_vis) and arrays.mesh is not None)
    o.mesh = arrays.mesh.id if arrays.mesh is not None else wp.uint64(0)
    o.ray_offset = 1e-3  # mm: far above float32 rounding of positions (~3e-5 mm), far below any occluder size
    o.plane_origin = wp.vec3(*rig.sample.origin)
    o.plane_x = wp.vec3(*rig.sample.x_axis)
    o.plane_y = wp.vec3(*rig.sample.y_axis)
    if arrays.mesh is not None:  # the frame: a ring of height h around a square window (HolderFrame.mesh)
        o.occluder_top = rig.frame.height
        o.occluder_outer = rig.frame.outer_size / 2 + 1e-3  # margins: float32 rounding of mm coordinates
        o.occluder_hole = rig.frame.inner_size / 2 - 1e-3
    return o


# --- inputs -----------------------------------------------------------------------------------------
def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


def validate_points(position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, transparency=None):
    """Check and normalise per-point inputs to numpy float64: (P,3) x5, (P,) x3. Clear errors."""
    def arr(name, x):
        if _is_torch(x):
            x = x.detach().cpu().numpy()
        a = np.asarray(x, dtype=np.float64)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or Inf")
        return a

    pos = arr("position", position)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"position must have shape (P, 3), got {pos.shape}")
    P = pos.shape[0]

    def vec(name, x):
        a = arr(name, x)
        if a.shape != (P, 3):
            if a.shape in ((P,), (P, 1)) and name.startswith("rho"):
                a = np.repeat(a.reshape(P, 1), 3, axis=1)
            else:
                raise ValueError(f"{name} must have shape ({P}, 3) like position, got {a.shape}")
        return a

    def scal(name, x):
        a = arr(name, x).reshape(-1) if np.ndim(x) else np.full(P, float(x))
        if a.shape != (P,):
            raise ValueError(f"{name} must have shape ({P},) like position, got {np.shape(x)}")
        return a

    n, t = vec("normal", normal), vec("tangent", tangent)
    rd, rs = vec("rho_d", rho_d), vec("rho_s", rho_s)
    ax, ay = scal("alpha_x", alpha_x), scal("alpha_y", alpha_y)
    check_material(n, t, rd, rs, ax, ay)
    beta = np.zeros(P) if transparency is None else scal("transparency", transparency)
    if np.any((beta < 0) | (beta > 1)):
        raise ValueError("transparency must lie in [0, 1]")
    return pos, n, t, rd, rs, ax, ay, beta


def validate_patterns(patterns, num_leds: int) -> np.ndarray:
    """(K, L, 3) or (K, L) relative LED drive; PatternSet objects give their 8-bit weights."""
    if hasattr(patterns, "weights") and hasattr(patterns, "levels"):
        patterns = patterns.weights
    if _is_torch(patterns):
        patterns = patterns.detach().cpu().numpy()
    w = np.asarray(patterns, dtype=np.float64)
    if w.ndim == 2:
        w = np.repeat(w[..., None], 3, axis=2)
    if w.ndim != 3 or w.shape[1:] != (num_leds, 3):
        raise ValueError(f"patterns must have shape (K, {num_leds}, 3) or (K, {num_leds}), got {np.shape(patterns)}")
    if not np.all(np.isfinite(w)):
        raise ValueError("patterns contain NaN or Inf")
    return w


# --- numpy path ---------------------------------------------------------------------------------------
def _device_inputs(rig, device, dtype, camera, pos, n, t, rd, rs, ax, ay, beta, requires_grad=False):
    arrays = rig_arrays(rig, device, dtype)
    vec, scal = (wp.vec3d, wp.float64) if dtype == "float64" else (wp.vec3f, wp.float32)
    npd = np.float64 if dtype == "float64" else np.float32
    cam_name = camera or next(iter(rig.cameras))
    if cam_name not in arrays.cameras:
        raise KeyError(f"rig {rig.name!r} has no camera {cam_name!r}; it has {list(rig.cameras)}")

    def a(x, t_):
        return wp.array(np.ascontiguousarray(x, dtype=npd), dtype=t_, device=device, requires_grad=requires_grad)

    pts = K.point_inputs(a(pos, vec), a(n, vec), a(t, vec), a(rd, vec), a(rs, vec), a(ax, scal), a(ay, scal),
                         a(beta, scal), arrays.cameras[cam_name], device)
    return arrays, pts


def _led_inputs(arrays: RigArrays, conv: Convention):
    return [arrays.lpos, arrays.lnrm, arrays.lu, arrays.lint if conv.rig_intensity else arrays.lint_unit,
            arrays.prof if conv.rig_profile else arrays.prof_lambert, arrays.lbot]

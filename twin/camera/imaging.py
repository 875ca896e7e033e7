"""Camera image formation: what each camera pixel sees, and its radiance under lighting patterns.

The path of a pixel:
  1. rays through K and the OpenCV distortion (undistortion by 20 fixed-point steps, as
     `Camera.undistort`); S x S stratified sub-pixel rays per pixel, S chosen from the ratio of the pixel's
     footprint on the sample plane to the texel size, so that texels are filtered over the pixel footprint
     (box filter);
  2. the hit: the holder frame's top face (with its ArUco markers, bit patterns from OpenCV's
     dictionary), else the sample plane: the sample's maps inside their extent, the translucent acrylic
     board elsewhere (up to the board's edge), else nothing (black);
  3. the surface's parameters there: bilinear texel lookup for the sample (normals and tangents
     re-normalised and re-orthogonalised), fixed materials for frame, markers and board;
  4. the radiance under each pattern, through the Warp forward model (Eq. 1-2 with the rig's LED
     intensities, Psi, visibility and the bottom LEDs through the acrylic and the transparency map),
     averaged over the sub-pixel rays, then the LED-RGB -> camera-RGB crosstalk and the vignetting.
The frame's 1.5 mm inner walls are not modelled as seen surfaces (both cameras look at them at < 45 deg
from above; they cover < 1 px at the modelled resolutions); they do cast shadows (twin.optics.forward's V).

Where it runs. Steps 1-3 are `trace_kernel` (float64, one thread per sub-pixel ray) and step 4 is the
contraction-free lumitexel kernel (twin.optics.lumitexel's `*_exact`), a float64 projection onto the
patterns (torch: cuBLAS / the CPU's BLAS), and `finish_kernel` (float64: sub-pixel mean, crosstalk,
vignetting, one rounding to float32). Everything stays on the device the caller names: on CUDA the
images are Warp arrays there, and only finished files leave it (twin.capture). The same kernels run on the
CPU.

Why float64 and no FMA contraction: the capture must give the same raw bytes on the CPU and on CUDA
(twin.camera.sensor). Without contraction, +, -, *, / and sqrt round identically on both devices, so the
traced surfaces and the lumitexels are bit-identical (for rigs whose LED profile needs no transcendental
function: the built-in rigs' cosine profile with exponent 1). The projection sums float32 lumitexel x
8-bit weight products, each exact in float64, in float64: whatever order the two BLAS libraries choose, the
sums differ by at most ~L 2^-53 relative, so their float32 rounding differs only when a sum lies that close
to a rounding boundary (at most ~1e-5 of the values, typically far fewer), and a 1-ulp radiance difference
moves a raw value in ~6e-5 of those cases (twin.camera.sensor). Measured: the mini captures of
docs/performance.md are byte-identical on the CPU and a CUDA GPU.

Only what a photo needs is rendered: the patterns are grouped by the LED classes they light (upper,
bottom), and each group evaluates only the LEDs its patterns light (the bottom-lit photos: the bottom LEDs
only; the others: the upper ones).

`trace_pixels_numpy` and `render_reference` are the numpy / float32-kernel implementations this module
had before (the oracles of tests/test_imaging.py and the same-work baseline of `hemicube bench capture`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import warp as wp

# forward only (nothing here is differentiated): no adjoint code, about half the compile time of a cold kernel
# cache (compilation counts in the end-to-end run; docs/performance.md)
wp.set_module_options({"fast_math": False, "fuse_fp": False, "enable_backward": False})

# Materials of the rig's own surfaces (ASSUMED; diffuse albedo, specular albedo, isotropic alpha).
FRAME_MATERIAL = (0.45, 0.8, 0.25)  # bead-blasted aluminium
MARKER_WHITE = (0.85, 0.0, 0.5)  # printed marker: matte paper
MARKER_BLACK = (0.03, 0.0, 0.5)
BOARD_MATERIAL = (0.7, 0.05, 0.2)  # translucent white acrylic, seen from above
BOARD_HALF_SIZE = 300.0  # mm, half side of the acrylic board the sample rests on (ASSUMED)
UNDISTORT_ITERATIONS = 20  # Camera.undistort's fixed-point steps

KIND_NONE, KIND_SAMPLE, KIND_FRAME, KIND_MARKER, KIND_BOARD = 0, 1, 2, 3, 4
_FRAME = wp.constant(wp.vec3d(*FRAME_MATERIAL))  # the materials as kernel constants
_WHITE = wp.constant(wp.vec3d(*MARKER_WHITE))
_BLACK = wp.constant(wp.vec3d(*MARKER_BLACK))
_BOARD = wp.constant(wp.vec3d(*BOARD_MATERIAL))
RENDER_CHUNK_BYTES = {"cpu": 1 << 28, "cuda": 1 << 33}  # lumitexels of one chunk (float32 RGB), per device kind


@dataclass(frozen=True)
class PixelSurfaces:
    """Per sub-pixel ray (N = H * W * S * S, pixel-major): the surface point and its parameters. Fields are
    Warp arrays on the device that traced them (`trace_pixels`; `host()` copies them to numpy) or numpy
    arrays (`trace_pixels_numpy`). `rows`: the camera rows traced (None: all)."""

    height: int
    width: int
    supersample: int
    position: object  # (N, 3) float32
    normal: object
    tangent: object
    rho_d: object
    rho_s: object
    alpha_x: object  # (N,) float32
    alpha_y: object
    transparency: object
    kind: object  # (N,) KIND_*
    texel: object  # (N, 2) float64 continuous (row, col) in the sample's maps, NaN off the sample
    rows: np.ndarray | None = None

    FIELDS = ("position", "normal", "tangent", "rho_d", "rho_s", "alpha_x", "alpha_y", "transparency", "kind",
              "texel")

    def host(self) -> "PixelSurfaces":
        """The same surfaces with numpy fields."""
        return replace(self, **{f: _numpy(getattr(self, f)) for f in self.FIELDS})

    def forward_args(self, index=slice(None)) -> dict:
        h = self.host()
        return dict(position=h.position[index], normal=h.normal[index], tangent=h.tangent[index],
                    rho_d=h.rho_d[index], rho_s=h.rho_s[index], alpha_x=h.alpha_x[index],
                    alpha_y=h.alpha_y[index])

    def pixel_texel(self) -> np.ndarray:
        """(H, W, 2) the true texel coordinate of each pixel (mean over its rays on the sample; the
        ground-truth sidecar)."""
        S = self.supersample
        t = _numpy(self.texel).reshape(self.height, self.width, S * S, 2)
        if S == 1:
            return t[:, :, 0]
        import warnings

        with warnings.catch_warnings():  # all-NaN off the sample: the mean is NaN, as intended
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmean(t, axis=2)


def _numpy(a):
    return a.numpy() if isinstance(a, wp.array) else np.asarray(a)


def choose_supersampling(camera, sample_plane, texel_mm: float, limit: int = 4) -> int:
    """S such that S x S rays sample every texel under the pixel footprint at the sample's centre."""
    uv, _ = camera.project(np.array([sample_plane.origin]))
    hits = camera.plane_points(np.array([uv[0], uv[0] + [1.0, 0.0]]), sample_plane.origin, sample_plane.normal)
    footprint = np.linalg.norm(hits[1] - hits[0])
    return int(np.clip(np.ceil(footprint / texel_mm), 1, limit))


def _marker_bits(frame) -> np.ndarray:
    """(M, B, B) bool, True = white, from OpenCV's ArUco dictionary (border included)."""
    import cv2

    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, frame.marker_dictionary))
    side = d.markerSize + 2
    return np.stack([cv2.aruco.generateImageMarker(d, int(i), side) > 127 for i in frame.marker_ids])


def _supersampling(rig, camera_name: str, maps, supersample):
    # no texture to filter on the empty board: one ray per pixel
    if supersample:
        return int(supersample)
    if maps is None:
        return 1
    return choose_supersampling(rig.camera(camera_name), rig.sample, maps.size_mm / maps.rho_d.shape[1])


# --- steps 1-3 in Warp ------------------------------------------------------------------------------
@wp.struct
class TraceScene:
    """A camera and what it can hit, in float64 (rig units)."""

    kinv: wp.mat22d  # inverse of K's upper-left 2x2
    pp: wp.vec2d  # principal point
    dist_k: wp.vec3d  # k1, k2, k3
    dist_p: wp.vec2d  # p1, p2
    rt: wp.mat33d  # R^T: camera -> world directions
    centre: wp.vec3d
    width: int
    supersample: int
    row0: int  # first traced camera row (a crop's offset; 0 for the whole image)
    origin: wp.vec3d  # sample plane
    normal: wp.vec3d
    x_axis: wp.vec3d
    y_axis: wp.vec3d
    board_half: wp.float64
    has_frame: int
    frame_height: wp.float64
    frame_outer_half: wp.float64
    frame_inner_half: wp.float64
    marker_tl: wp.array(dtype=wp.vec3d)  # per marker: top-left corner, edge vectors to top-right and
    marker_ex: wp.array(dtype=wp.vec3d)  # bottom-left
    marker_ey: wp.array(dtype=wp.vec3d)
    marker_bits: wp.array3d(dtype=wp.int32)  # (M, B, B), 1 = white
    has_maps: int
    maps_half: wp.float64  # half the sample's side
    maps_size: wp.float64
    rho_d: wp.array3d(dtype=wp.float32)  # (Hm, Wm, 3)
    rho_s: wp.array3d(dtype=wp.float32)
    alpha: wp.array3d(dtype=wp.float32)  # (Hm, Wm, 2)
    nrm: wp.array3d(dtype=wp.float32)
    tan: wp.array3d(dtype=wp.float32)
    beta: wp.array2d(dtype=wp.float32)


@wp.func
def _hit_plane(sc: TraceScene, d: wp.vec3d, height: wp.float64):
    """(t, x, y) of the ray c + t d on the plane `height` above the sample plane: t along the ray, (x, y)
    in the plane's axes."""
    denom = wp.dot(d, sc.normal)
    t = wp.dot(sc.origin + sc.normal * height - sc.centre, sc.normal) / denom
    q = sc.centre + d * t - sc.origin
    return wp.vec3d(t, wp.dot(q, sc.x_axis), wp.dot(q, sc.y_axis))


@wp.func
def _bilinear3(a: wp.array3d(dtype=wp.float32), r0: int, r1: int, c0: int, c1: int, fr: wp.float64,
               fc: wp.float64, ch: int):
    one = wp.float64(1.0)
    top = wp.float64(a[r0, c0, ch]) * (one - fc) + wp.float64(a[r0, c1, ch]) * fc
    bot = wp.float64(a[r1, c0, ch]) * (one - fc) + wp.float64(a[r1, c1, ch]) * fc
    return top * (one - fr) + bot * fr


@wp.func
def _bilinear_vec(a: wp.array3d(dtype=wp.float32), r0: int, r1: int, c0: int, c1: int, fr: wp.float64,
                  fc: wp.float64):
    return wp.vec3d(_bilinear3(a, r0, r1, c0, c1, fr, fc, 0), _bilinear3(a, r0, r1, c0, c1, fr, fc, 1),
                    _bilinear3(a, r0, r1, c0, c1, fr, fc, 2))


@wp.kernel
def trace_kernel(sc: TraceScene, pos: wp.array(dtype=wp.vec3f), nrm: wp.array(dtype=wp.vec3f),
                 tan: wp.array(dtype=wp.vec3f), rd: wp.array(dtype=wp.vec3f), rs: wp.array(dtype=wp.vec3f),
                 ax: wp.array(dtype=wp.float32), ay: wp.array(dtype=wp.float32),
                 beta: wp.array(dtype=wp.float32), kind: wp.array(dtype=wp.int32),
                 texel: wp.array(dtype=wp.vec2d)):
    """Steps 1-3 for one sub-pixel ray (the numpy twin: trace_pixels_numpy)."""
    i = wp.tid()
    S = sc.supersample
    pix = i // (S * S)
    sub = i % (S * S)
    one = wp.float64(1.0)
    half = wp.float64(0.5)
    inv_s = one / wp.float64(S)
    u = wp.float64(pix % sc.width) + ((wp.float64(sub % S) + half) * inv_s - half)
    v = wp.float64(sc.row0 + pix // sc.width) + ((wp.float64(sub // S) + half) * inv_s - half)
    # 1. the ray: K^-1, then Camera.undistort's fixed point, then to world
    xy_d = sc.kinv * (wp.vec2d(u, v) - sc.pp)
    x = xy_d[0]
    y = xy_d[1]
    two = wp.float64(2.0)
    for _ in range(UNDISTORT_ITERATIONS):
        r2 = x * x + y * y
        radial = one + r2 * (sc.dist_k[0] + r2 * (sc.dist_k[1] + r2 * sc.dist_k[2]))
        dx = two * sc.dist_p[0] * x * y + sc.dist_p[1] * (r2 + two * x * x)
        dy = sc.dist_p[0] * (r2 + two * y * y) + two * sc.dist_p[1] * x * y
        x_next = (xy_d[0] - dx) / radial
        y = (xy_d[1] - dy) / radial
        x = x_next
    d = wp.normalize(sc.rt * wp.vec3d(x, y, one))
    # 2-3. the hit and its material
    k = KIND_NONE
    p = sc.origin  # rays that leave the rig: a dark dummy point, masked out later
    mat = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.3))  # rho_d, rho_s, alpha
    b = wp.float64(0.0)
    zero = wp.float64(0.0)
    if sc.has_frame != 0:  # the holder frame's top face first: it is above the sample plane
        h = _hit_plane(sc, d, sc.frame_height)
        cheb = wp.max(wp.abs(h[1]), wp.abs(h[2]))
        if h[0] > zero and cheb <= sc.frame_outer_half and cheb >= sc.frame_inner_half:
            p = sc.centre + d * h[0]
            k = KIND_FRAME
            mat = _FRAME
            B = sc.marker_bits.shape[1]
            for m in range(sc.marker_tl.shape[0]):  # the last marker containing the point wins (as numpy)
                q = p - sc.marker_tl[m]
                ex = sc.marker_ex[m]
                ey = sc.marker_ey[m]
                a = wp.dot(q, ex) / wp.dot(ex, ex)
                bb = wp.dot(q, ey) / wp.dot(ey, ey)
                if a >= zero and a < one and bb >= zero and bb < one:
                    k = KIND_MARKER
                    bit_row = wp.clamp(int(bb * wp.float64(B)), 0, B - 1)
                    bit_col = wp.clamp(int(a * wp.float64(B)), 0, B - 1)
                    if sc.marker_bits[m, bit_row, bit_col] != 0:
                        mat = _WHITE
                    else:
                        mat = _BLACK
    n_out = sc.normal
    t_out = sc.x_axis
    rd_out = wp.vec3d(mat[0], mat[0], mat[0])
    rs_out = wp.vec3d(mat[1], mat[1], mat[1])
    ax_out = mat[2]
    ay_out = mat[2]
    tex = wp.vec2d(wp.float64(wp.nan), wp.float64(wp.nan))
    if k == KIND_NONE:
        h = _hit_plane(sc, d, zero)
        if h[0] > zero and wp.max(wp.abs(h[1]), wp.abs(h[2])) <= sc.board_half:
            p = sc.centre + d * h[0]
            k = KIND_BOARD
            rd_out = wp.vec3d(_BOARD[0], _BOARD[0], _BOARD[0])
            rs_out = wp.vec3d(_BOARD[1], _BOARD[1], _BOARD[1])
            ax_out = _BOARD[2]
            ay_out = ax_out
            b = one
            if sc.has_maps != 0 and wp.abs(h[1]) < sc.maps_half and wp.abs(h[2]) < sc.maps_half:
                Hm = sc.rho_d.shape[0]
                Wm = sc.rho_d.shape[1]
                col = (h[1] + sc.maps_half) / sc.maps_size * wp.float64(Wm) - half  # texel-centre convention
                row = (h[2] + sc.maps_half) / sc.maps_size * wp.float64(Hm) - half
                tex = wp.vec2d(row, col)
                k = KIND_SAMPLE
                r0 = wp.clamp(int(wp.floor(row)), 0, Hm - 1)
                c0 = wp.clamp(int(wp.floor(col)), 0, Wm - 1)
                r1 = wp.min(r0 + 1, Hm - 1)
                c1 = wp.min(c0 + 1, Wm - 1)
                fr = wp.clamp(row - wp.float64(r0), zero, one)
                fc = wp.clamp(col - wp.float64(c0), zero, one)
                rd_out = _bilinear_vec(sc.rho_d, r0, r1, c0, c1, fr, fc)
                rs_out = _bilinear_vec(sc.rho_s, r0, r1, c0, c1, fr, fc)
                ax_out = _bilinear3(sc.alpha, r0, r1, c0, c1, fr, fc, 0)
                ay_out = _bilinear3(sc.alpha, r0, r1, c0, c1, fr, fc, 1)
                nn = _bilinear_vec(sc.nrm, r0, r1, c0, c1, fr, fc)
                nn = nn / wp.length(nn)
                tt = _bilinear_vec(sc.tan, r0, r1, c0, c1, fr, fc)
                tt = tt - wp.dot(tt, nn) * nn
                n_out = nn
                t_out = tt / wp.length(tt)
                bc = wp.float64(sc.beta[r0, c0]) * (one - fc) + wp.float64(sc.beta[r0, c1]) * fc
                bn = wp.float64(sc.beta[r1, c0]) * (one - fc) + wp.float64(sc.beta[r1, c1]) * fc
                b = bc * (one - fr) + bn * fr
    pos[i] = wp.vec3f(p)
    nrm[i] = wp.vec3f(n_out)
    tan[i] = wp.vec3f(t_out)
    rd[i] = wp.vec3f(rd_out)
    rs[i] = wp.vec3f(rs_out)
    ax[i] = wp.float32(ax_out)
    ay[i] = wp.float32(ay_out)
    beta[i] = wp.float32(b)
    kind[i] = k
    texel[i] = tex


def _trace_scene(rig, cam, maps, S: int, row0: int, device) -> TraceScene:
    sc = TraceScene()
    K = np.asarray(cam.K, np.float64)
    sc.kinv = wp.mat22d(*np.linalg.inv(K[:2, :2]).ravel())
    sc.pp = wp.vec2d(*K[:2, 2])
    k1, k2, p1, p2, k3 = (float(v) for v in cam.dist)
    sc.dist_k = wp.vec3d(k1, k2, k3)
    sc.dist_p = wp.vec2d(p1, p2)
    sc.rt = wp.mat33d(*np.asarray(cam.R, np.float64).T.ravel())
    sc.centre = wp.vec3d(*cam.centre)
    sc.width, sc.supersample, sc.row0 = cam.width, S, row0
    sp = rig.sample
    sc.origin, sc.normal = wp.vec3d(*sp.origin), wp.vec3d(*sp.normal)
    sc.x_axis, sc.y_axis = wp.vec3d(*sp.x_axis), wp.vec3d(*sp.y_axis)
    sc.board_half = BOARD_HALF_SIZE
    fr = rig.frame
    corners = np.zeros((0, 4, 3)) if fr is None else np.asarray(fr.marker_corners, np.float64)
    bits = np.zeros((0, 1, 1), np.int32) if fr is None or not len(corners) else _marker_bits(fr).astype(np.int32)
    sc.has_frame = int(fr is not None)
    sc.frame_height = fr.height if fr is not None else 0.0
    sc.frame_outer_half = fr.outer_size / 2 if fr is not None else 0.0
    sc.frame_inner_half = fr.inner_size / 2 if fr is not None else 0.0

    def v3(a):
        return wp.array(np.ascontiguousarray(a, np.float64).reshape(-1, 3), dtype=wp.vec3d, device=device)

    sc.marker_tl = v3(corners[:, 0])
    sc.marker_ex = v3(corners[:, 1] - corners[:, 0])
    sc.marker_ey = v3(corners[:, 3] - corners[:, 0])
    sc.marker_bits = wp.array(bits, dtype=wp.int32, device=device)
    sc.has_maps = int(maps is not None)

    def f32(a, shape=None):
        a = np.zeros(shape, np.float32) if a is None else np.ascontiguousarray(a, np.float32)
        return wp.array(a, dtype=wp.float32, device=device)

    m = maps
    sc.maps_half = m.size_mm / 2 if m is not None else 0.0
    sc.maps_size = m.size_mm if m is not None else 1.0
    sc.rho_d = f32(m.rho_d if m else None, (1, 1, 3))
    sc.rho_s = f32(m.rho_s if m else None, (1, 1, 3))
    sc.alpha = f32(m.alpha if m else None, (1, 1, 2))
    sc.nrm = f32(m.normal if m else None, (1, 1, 3))
    sc.tan = f32(m.tangent if m else None, (1, 1, 3))
    sc.beta = f32(m.transparency if m else None, (1, 1))
    return sc


def trace_pixels(rig, camera_name: str, maps=None, supersample: int | None = None, device="cpu",
                 rows: tuple[int, int] | None = None) -> PixelSurfaces:
    """Trace every pixel of a camera (or of its rows start..stop-1) into the rig (steps 1-3) on `device`:
    Warp-array surfaces there. `maps`: a twin.materials.samples.SVBRDFMaps, or None for the empty board
    (the transparency reference)."""
    from twin.optics.inputs import _init

    _init()
    cam = rig.camera(camera_name)
    S = _supersampling(rig, camera_name, maps, supersample)
    r0, r1 = (0, cam.height) if rows is None else (int(rows[0]), int(rows[1]))
    if not 0 <= r0 < r1 <= cam.height:
        raise ValueError(f"rows {rows} outside the camera's 0..{cam.height}")
    N = (r1 - r0) * cam.width * S * S
    out = {f: wp.empty(N, dtype=t, device=device) for f, t in (
        ("position", wp.vec3f), ("normal", wp.vec3f), ("tangent", wp.vec3f), ("rho_d", wp.vec3f),
        ("rho_s", wp.vec3f), ("alpha_x", wp.float32), ("alpha_y", wp.float32), ("transparency", wp.float32),
        ("kind", wp.int32), ("texel", wp.vec2d))}
    wp.launch(trace_kernel, dim=N, inputs=[_trace_scene(rig, cam, maps, S, r0, device)],
              outputs=[out[f] for f in PixelSurfaces.FIELDS], device=device)
    return PixelSurfaces(r1 - r0, cam.width, S, **out, rows=None if rows is None else np.arange(r0, r1))


# --- step 4 -------------------------------------------------------------------------------------------
@wp.kernel
def finish_kernel(b_r: wp.array2d(dtype=wp.float64), b_g: wp.array2d(dtype=wp.float64),
                  b_b: wp.array2d(dtype=wp.float64), kind: wp.array(dtype=wp.int32), pixel0: int, ray0: int,
                  S2: int, width: int, images: wp.array(dtype=int), crosstalk: wp.mat33d,
                  gain: wp.array2d(dtype=wp.float64), out: wp.array3d(dtype=wp.vec3f)):
    """One (pixel, pattern) of a chunk: the mean over the pixel's live sub-pixel rays of the projected
    lumitexels (b_*: (rays of the chunk, patterns of the group)), the crosstalk, the vignetting, then one
    rounding to float32 into out[images[k], row, col]."""
    q, k = wp.tid()
    pix = pixel0 + q
    acc = wp.vec3d()
    for s in range(S2):
        ray = pix * S2 + s
        if kind[ray] != KIND_NONE:
            r = ray - ray0
            acc += wp.vec3d(b_r[r, k], b_g[r, k], b_b[r, k])
    row = pix // width
    col = pix % width
    rgb = (crosstalk * acc) * (gain[row, col] / wp.float64(S2))
    out[images[k], row, col] = wp.vec3f(rgb)


def pattern_groups(weights: np.ndarray, is_bottom: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(pattern indices, LED indices)]: the patterns grouped by the LED classes (upper, bottom) they light,
    each group with the LEDs any of its patterns lights (a group of dark patterns evaluates no LED)."""
    lit = np.any(weights != 0, axis=2)  # (K, L)
    sig = np.stack([np.any(lit & ~is_bottom, axis=1), np.any(lit & is_bottom, axis=1)], axis=1)
    groups = []
    for key in np.unique(sig, axis=0):
        ks = np.flatnonzero(np.all(sig == key, axis=1))
        groups.append((ks, np.flatnonzero(np.any(lit[ks], axis=0))))
    return groups


def optics_gain(cam, flat_field=None) -> np.ndarray:
    """(H, W) float64: the vignetting factor times the flat-field multiplier, if any (the rig's own map for
    the camera, `Rig.flat_fields`, unless the caller gives another)."""
    from twin.camera.sensor import vignetting_factor

    gain = vignetting_factor(cam.K, cam.width, cam.height, cam.sensor.vignetting)
    return gain if flat_field is None else gain * np.asarray(flat_field, np.float64)


def render_device(rig, camera_name: str, surfaces: PixelSurfaces, patterns, *, device="cpu",
                  flat_field: np.ndarray | None = None, chunk_bytes: int | None = None) -> wp.array:
    """Step 4 on `device`: radiance images (K, H, W) vec3f (a Warp array there) in W m^-2 sr^-1 under
    `patterns` (K, L, 3) relative drive (8-bit levels / 255). The surfaces come from trace_pixels on the
    same device (numpy surfaces are copied there)."""
    import torch

    from twin.optics.inputs import _init, validate_patterns

    _init()
    w = validate_patterns(patterns, rig.num_leds)
    dev = wp.get_device(device)
    if not dev.is_cuda:
        return _render(rig, camera_name, surfaces, w, dev, flat_field, chunk_bytes)
    # Warp's launches and torch's products share torch's stream, so each reads what the other wrote; the
    # device's Warp stream then waits for it, so later Warp work (the sensor) sees the images
    stream = wp.stream_from_torch(torch.cuda.current_stream(wp.device_to_torch(dev)))
    with wp.ScopedStream(stream):
        out = _render(rig, camera_name, surfaces, w, dev, flat_field, chunk_bytes)
    wp.get_stream(dev).wait_stream(stream)
    return out


def _render(rig, camera_name, surfaces, w, dev, flat_field, chunk_bytes):
    import torch

    from twin.optics import lumitexel as KL
    from twin.optics.inputs import CONVENTIONS, _led_inputs, make_options, rig_arrays

    cam = rig.camera(camera_name)
    tdev = wp.device_to_torch(dev)
    s = _on_device(surfaces, dev)
    H, Wd, S2 = s.height, s.width, s.supersample ** 2
    out = wp.zeros((w.shape[0], H, Wd), dtype=wp.vec3f, device=dev)
    ff = flat_field if flat_field is not None else rig.flat_fields.get(camera_name)
    gain = wp.array(optics_gain(cam, ff)[_rows(s)], dtype=wp.float64, device=dev)
    crosstalk = wp.mat33d(*np.asarray(cam.sensor.crosstalk, np.float64).ravel())
    budget = chunk_bytes or RENDER_CHUNK_BYTES["cuda" if dev.is_cuda else "cpu"]
    for ks, leds in pattern_groups(w, rig.is_bottom):
        if leds.size == 0:
            continue  # dark patterns: the zeros already there
        sub = replace(rig, leds=rig.leds.subset(leds))
        arrays = rig_arrays(sub, dev)
        o = make_options(sub, arrays, "physical", "separable", "schlick", 1.5, None)
        led_in = _led_inputs(arrays, CONVENTIONS["physical"])
        # (3, L_g, K_g) float64: each 8-bit weight and each float32 lumitexel product is exact in float64
        wg = torch.as_tensor(np.ascontiguousarray(w[ks][:, leds].transpose(2, 1, 0)), dtype=torch.float64,
                             device=tdev)
        images = wp.array(ks.astype(np.int32), dtype=int, device=dev)
        pixels = max(1, budget // (S2 * leds.size * 12))
        for p0 in range(0, H * Wd, pixels):
            p1 = min(p0 + pixels, H * Wd)
            r0, r1 = p0 * S2, p1 * S2
            pts = KL.point_inputs(s.position[r0:r1], s.normal[r0:r1], s.tangent[r0:r1], s.rho_d[r0:r1],
                                  s.rho_s[r0:r1], s.alpha_x[r0:r1], s.alpha_y[r0:r1], s.transparency[r0:r1],
                                  arrays.cameras[camera_name], dev, exact=True)
            m = wp.empty((r1 - r0, leds.size), dtype=wp.vec3f, device=dev)
            wp.launch(KL.lumitexel_kernel_exact, dim=m.shape, inputs=[*pts, *led_in, o], outputs=[m], device=dev)
            mt = wp.to_torch(m)  # (rays, L_g, 3)
            b = [wp.from_torch(torch.matmul(mt[..., c].to(torch.float64), wg[c]).contiguous(), dtype=wp.float64)
                 for c in range(3)]
            wp.launch(finish_kernel, dim=(p1 - p0, ks.size),
                      inputs=[*b, s.kind, p0, r0, S2, Wd, images, crosstalk, gain], outputs=[out], device=dev)
    return out


def render(rig, camera_name: str, surfaces: PixelSurfaces, patterns, *, device="cpu",
           flat_field: np.ndarray | None = None) -> np.ndarray:
    """`render_device`, copied to numpy: (K, H, W, 3) float32."""
    return render_device(rig, camera_name, surfaces, patterns, device=device, flat_field=flat_field).numpy()


def _rows(s: PixelSurfaces):
    return slice(None) if s.rows is None else s.rows


def _on_device(s: PixelSurfaces, dev) -> PixelSurfaces:
    """The surfaces as Warp arrays on `dev` (the forward kernels' float32 inputs)."""
    types = {"position": wp.vec3f, "normal": wp.vec3f, "tangent": wp.vec3f, "rho_d": wp.vec3f, "rho_s": wp.vec3f,
             "alpha_x": wp.float32, "alpha_y": wp.float32, "transparency": wp.float32, "kind": wp.int32,
             "texel": wp.vec2d}

    def move(f):
        a = getattr(s, f)
        if isinstance(a, wp.array):
            return a if a.device == dev else a.to(dev)
        npd = np.float64 if types[f] == wp.vec2d else (np.int32 if f == "kind" else np.float32)
        return wp.array(np.ascontiguousarray(a, npd), dtype=types[f], device=dev)

    return replace(s, **{f: move(f) for f in PixelSurfaces.FIELDS})


# --- the numpy implementations: oracles and the bench's same-work baseline ----------------------------
def trace_pixels_numpy(rig, camera_name: str, maps=None, supersample: int | None = None,
                       rows=None) -> PixelSurfaces:
    """Steps 1-3 in numpy float64 (`trace_kernel`'s oracle), of the camera rows `rows` (default: all)."""
    cam = rig.camera(camera_name)
    sp = rig.sample
    o, n = np.asarray(sp.origin), np.asarray(sp.normal)
    xa, ya = np.asarray(sp.x_axis), sp.y_axis
    S = _supersampling(rig, camera_name, maps, supersample)
    rows_ = np.arange(cam.height) if rows is None else np.asarray(rows)
    H, W = len(rows_), cam.width
    sub = (np.arange(S) + 0.5) / S - 0.5  # stratified sub-pixel offsets, fixed: deterministic
    v, u, sv, su = np.meshgrid(rows_, np.arange(W), sub, sub, indexing="ij")
    uv = np.stack([(u + su).ravel(), (v + sv).ravel()], axis=1)
    d = cam.pixel_rays(uv)
    c = cam.centre
    N = len(d)

    def hit_plane(height):
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((o + n * height - c) @ n) / denom
        p = c + d * t[:, None]
        q = p - o
        return t, p, q @ xa, q @ ya

    kind = np.zeros(N, np.int32)
    pos = np.zeros((N, 3))
    rd, rs, al, beta = np.zeros(N), np.zeros(N), np.full(N, 0.3), np.zeros(N)
    rd3 = np.zeros((N, 3))
    rs3 = np.zeros((N, 3))
    nrm = np.tile(n, (N, 1))
    tan = np.tile(xa, (N, 1))
    ax = np.full(N, 0.3)
    ay = np.full(N, 0.3)
    texel = np.full((N, 2), np.nan)

    def assign(sel, material, k):
        rd[sel], rs[sel], al[sel] = material
        kind[sel] = k

    # the holder frame's top face first: it is above the sample plane
    if rig.frame is not None:
        fr = rig.frame
        t, p, x, y = hit_plane(fr.height)
        ring = (t > 0) & (np.maximum(abs(x), abs(y)) <= fr.outer_size / 2) & \
               (np.maximum(abs(x), abs(y)) >= fr.inner_size / 2)
        pos[ring] = p[ring]
        assign(ring, FRAME_MATERIAL, KIND_FRAME)
        bits = _marker_bits(fr)
        B = bits.shape[1]
        for m, corners in enumerate(fr.marker_corners):
            tl, tr, _, bl = corners
            ex, ey = tr - tl, bl - tl
            q = p - tl
            a = q @ ex / (ex @ ex)
            b = q @ ey / (ey @ ey)
            inside = ring & (a >= 0) & (a < 1) & (b >= 0) & (b < 1)
            white = bits[m][np.clip((b[inside] * B).astype(int), 0, B - 1), np.clip((a[inside] * B).astype(int), 0, B - 1)]
            idx = np.flatnonzero(inside)
            assign(idx[white], MARKER_WHITE, KIND_MARKER)
            assign(idx[~white], MARKER_BLACK, KIND_MARKER)
    rest = kind == KIND_NONE
    t, p, x, y = hit_plane(0.0)
    on_board = rest & (t > 0) & (np.maximum(abs(x), abs(y)) <= BOARD_HALF_SIZE)
    pos[on_board] = p[on_board]
    assign(on_board, BOARD_MATERIAL, KIND_BOARD)
    beta[on_board] = 1.0
    rd3[:] = rd[:, None]
    rs3[:] = rs[:, None]
    ax[:] = al
    ay[:] = al
    if maps is not None:
        Hm, Wm = maps.rho_d.shape[:2]
        half = maps.size_mm / 2
        on_sample = on_board & (abs(x) < half) & (abs(y) < half)
        col = (x[on_sample] + half) / maps.size_mm * Wm - 0.5  # texel-centre convention (twin.materials.samples)
        row = (y[on_sample] + half) / maps.size_mm * Hm - 0.5
        texel[on_sample] = np.stack([row, col], axis=1)
        kind[on_sample] = KIND_SAMPLE
        look = _bilinear(maps, row, col)
        rd3[on_sample], rs3[on_sample] = look["rho_d"], look["rho_s"]
        ax[on_sample], ay[on_sample] = look["alpha"][:, 0], look["alpha"][:, 1]
        nn = look["normal"] / np.linalg.norm(look["normal"], axis=1, keepdims=True)
        tt = look["tangent"] - (look["tangent"] * nn).sum(1, keepdims=True) * nn
        tt /= np.linalg.norm(tt, axis=1, keepdims=True)
        nrm[on_sample], tan[on_sample] = nn, tt
        beta[on_sample] = look["transparency"][:, 0]
    off = kind == KIND_NONE  # rays that leave the rig: a dark dummy point, masked out later
    pos[off] = o
    return PixelSurfaces(H, W, S, pos, nrm, tan, rd3, rs3, ax, ay, beta, kind, texel,
                         rows=None if rows is None else rows_)


def _bilinear(maps, row, col) -> dict:
    Hm, Wm = maps.rho_d.shape[:2]
    r0 = np.clip(np.floor(row).astype(int), 0, Hm - 1)
    c0 = np.clip(np.floor(col).astype(int), 0, Wm - 1)
    r1, c1 = np.clip(r0 + 1, 0, Hm - 1), np.clip(c0 + 1, 0, Wm - 1)
    fr = np.clip(row - r0, 0, 1)[:, None]
    fc = np.clip(col - c0, 0, 1)[:, None]
    out = {}
    for name in ("rho_d", "rho_s", "alpha", "normal", "tangent", "transparency"):
        a = getattr(maps, name)
        a = a[..., None] if a.ndim == 2 else a
        out[name] = ((a[r0, c0] * (1 - fc) + a[r0, c1] * fc) * (1 - fr) + (a[r1, c0] * (1 - fc) + a[r1, c1] * fc) * fr)
    return out


def render_reference(rig, camera_name: str, surfaces: PixelSurfaces, patterns, *, device="cpu",
                     chunk: int = 16384, flat_field: np.ndarray | None = None) -> np.ndarray:
    """Step 4 as it was before the device render (`render`'s oracle and the bench's baseline): the public
    forward model's fused float32 kernel (twin.measurements) on every live ray, then the sub-pixel mean,
    crosstalk and vignetting in numpy. (K, H, W, 3) float32 of the surfaces' rows."""
    from twin.camera.sensor import apply_crosstalk
    from twin.optics.forward import measurements
    from twin.optics.inputs import validate_patterns

    cam = rig.camera(camera_name)
    h = surfaces.host()
    w = validate_patterns(patterns, rig.num_leds).astype(np.float32)
    K = w.shape[0]
    N = len(h.kind)
    out = np.zeros((N, K, 3), np.float32)
    live = np.flatnonzero(h.kind != KIND_NONE)
    for i in range(0, len(live), chunk):
        idx = live[i:i + chunk]
        out[idx] = measurements(rig, **h.forward_args(idx), patterns=w, transparency=h.transparency[idx],
                                camera=camera_name, device=device, method="fused")
    S2 = h.supersample ** 2
    img = out.reshape(h.height, h.width, S2, K, 3).mean(axis=2).transpose(2, 0, 1, 3)
    img = apply_crosstalk(img, cam.sensor.crosstalk)  # camera RGB = M @ LED RGB
    gain = optics_gain(cam, flat_field if flat_field is not None else rig.flat_fields.get(camera_name))[_rows(h)]
    return (img * gain[None, :, :, None]).astype(np.float32)

"""Camera image formation: what each camera pixel sees, and its radiance under lighting patterns.

The path of a pixel (issue "virtual capture", §2):
  1. rays through K and the OpenCV distortion (`Camera.pixel_rays`, undistortion by fixed point);
     S x S stratified sub-pixel rays per pixel, S chosen from the ratio of the pixel's footprint on the
     sample plane to the texel size, so that texels are filtered over the pixel footprint (box filter);
  2. the hit: the holder frame's top face (with its ArUco markers, bit patterns from OpenCV's
     dictionary), else the sample plane: the sample's maps inside their extent, the translucent acrylic
     board elsewhere (up to the board's edge), else nothing (black);
  3. the surface's parameters there: bilinear texel lookup for the sample (normals and tangents
     re-normalised and re-orthogonalised), fixed materials for frame, markers and board;
  4. the radiance under each pattern, through the Warp forward model (twin.optics.forward: Eq. 1-2 with the rig's
     LED intensities, Psi, visibility and the bottom LEDs through the acrylic and the transparency map),
     averaged over the sub-pixel rays, then the LED-RGB -> camera-RGB crosstalk and the vignetting.
The frame's 1.5 mm inner walls are not modelled as seen surfaces (both cameras look at them at < 45 deg
from above; they cover < 1 px at the modelled resolutions); they do cast shadows (twin.optics.forward's V).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Materials of the rig's own surfaces (ASSUMED; diffuse albedo, specular albedo, isotropic alpha).
FRAME_MATERIAL = (0.45, 0.8, 0.25)  # bead-blasted aluminium
MARKER_WHITE = (0.85, 0.0, 0.5)  # printed marker: matte paper
MARKER_BLACK = (0.03, 0.0, 0.5)
BOARD_MATERIAL = (0.7, 0.05, 0.2)  # translucent white acrylic, seen from above
BOARD_HALF_SIZE = 300.0  # mm, half side of the acrylic board the sample rests on (ASSUMED)

KIND_NONE, KIND_SAMPLE, KIND_FRAME, KIND_MARKER, KIND_BOARD = 0, 1, 2, 3, 4


@dataclass(frozen=True)
class PixelSurfaces:
    """Per sub-pixel ray (N = H * W * S * S, pixel-major): the surface point and its parameters."""

    height: int
    width: int
    supersample: int
    position: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    rho_d: np.ndarray
    rho_s: np.ndarray
    alpha_x: np.ndarray
    alpha_y: np.ndarray
    transparency: np.ndarray
    kind: np.ndarray  # KIND_*
    texel: np.ndarray  # (N, 2) continuous (row, col) in the sample's maps, NaN off the sample

    def forward_args(self, index=slice(None)) -> dict:
        return dict(position=self.position[index], normal=self.normal[index], tangent=self.tangent[index],
                    rho_d=self.rho_d[index], rho_s=self.rho_s[index], alpha_x=self.alpha_x[index],
                    alpha_y=self.alpha_y[index])

    def pixel_texel(self) -> np.ndarray:
        """(H, W, 2) the true texel coordinate of each pixel's central ray (the ground-truth sidecar)."""
        S = self.supersample
        t = self.texel.reshape(self.height, self.width, S * S, 2)
        if S == 1:
            return t[:, :, 0]
        with np.errstate(invalid="ignore"):  # all-NaN off the sample: the mean is NaN, as intended
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                return np.nanmean(t, axis=2)


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


def trace_pixels(rig, camera_name: str, maps=None, supersample: int | None = None) -> PixelSurfaces:
    """Trace every pixel of a camera into the rig (steps 1-3). `maps`: a twin.materials.samples.SVBRDFMaps, or
    None for the empty board (the transparency reference)."""
    cam = rig.camera(camera_name)
    sp = rig.sample
    o, n = np.asarray(sp.origin), np.asarray(sp.normal)
    xa, ya = np.asarray(sp.x_axis), sp.y_axis
    # no texture to filter on the empty board: one ray per pixel
    S = supersample or (choose_supersampling(cam, sp, maps.size_mm / maps.rho_d.shape[1]) if maps is not None else 1)
    H, W = cam.height, cam.width
    sub = (np.arange(S) + 0.5) / S - 0.5  # stratified sub-pixel offsets, fixed: deterministic
    v, u, sv, su = np.meshgrid(np.arange(H), np.arange(W), sub, sub, indexing="ij")
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

    kind = np.zeros(N, np.int8)
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
    return PixelSurfaces(H, W, S, pos, nrm, tan, rd3, rs3, ax, ay, beta, kind, texel)


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


def render(rig, camera_name: str, surfaces: PixelSurfaces, patterns: np.ndarray, *, device="cpu",
           chunk: int = 16384, method: str = "auto", flat_field: np.ndarray | None = None,
           **forward_kw) -> np.ndarray:
    """Step 4: radiance images (K, H, W, 3) float32 in W m^-2 sr^-1 under `patterns` (K, L, 3) relative
    drive (8-bit levels / 255). method: "fused" (twin.measurements' fused kernel), "materialise" (the
    lumitexels of a chunk of rays, then the projection: on the CPU one BLAS product per channel, on CUDA
    the projection kernel), or "auto" (fused on CUDA, materialise on the CPU, the faster there)."""
    from twin.camera.sensor import apply_crosstalk, vignetting_factor
    from twin.optics.forward import lumitexels, measurements
    from twin.optics.inputs import validate_patterns

    cam = rig.camera(camera_name)
    w = validate_patterns(patterns, rig.num_leds).astype(np.float32)
    K = w.shape[0]
    N = len(surfaces.kind)
    out = np.zeros((N, K, 3), np.float32)
    live = np.flatnonzero(surfaces.kind != KIND_NONE)
    cuda = str(device).startswith("cuda")
    if method == "auto":
        method = "fused" if cuda else "materialise"
    if method not in ("fused", "materialise"):
        raise ValueError(f"unknown render method {method!r}")
    for i in range(0, len(live), chunk):
        idx = live[i:i + chunk]
        args = surfaces.forward_args(idx)
        if cuda or method == "fused":
            out[idx] = measurements(rig, **args, patterns=w, transparency=surfaces.transparency[idx],
                                    camera=camera_name, device=device, method=method, **forward_kw)
        else:
            m = lumitexels(rig, **args, transparency=surfaces.transparency[idx], camera=camera_name,
                           device=device, **forward_kw)
            for c in range(3):  # one BLAS product per channel
                out[idx, :, c] = m[:, :, c] @ w[:, :, c].T
    S2 = surfaces.supersample ** 2
    img = out.reshape(surfaces.height, surfaces.width, S2, K, 3).mean(axis=2).transpose(2, 0, 1, 3)
    img = apply_crosstalk(img, cam.sensor.crosstalk)  # camera RGB = M @ LED RGB
    gain = vignetting_factor(cam.K, cam.width, cam.height, cam.sensor.vignetting)
    if flat_field is not None:
        gain = gain * flat_field
    return (img * gain[None, :, :, None]).astype(np.float32)

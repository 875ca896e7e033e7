"""`hemicube bench ...`: throughput figures as JSON, each with a same-run baseline.

bench lumitexel: LED-BRDF evaluations per second (points x LEDs / second) of
  * the Warp materialising kernels (lumitexels stored; lumitexel.materialise: the rows kernel on CUDA, its
    fast-math twin, and the one-thread-per-evaluation kernel the rows kernel replaced there, for the record),
    alone and followed by the projection onto the patterns (twin.measurements' method="materialise":
    forward.project, cuBLAS on CUDA; in float32, and with fast=True and tensor_cores=True, TF32),
  * the Warp fused kernel (64-pattern measurements, lumitexels never stored),
  * the baseline: a plain batched-torch version of the same formula (Eq. 1 with the same GGX,
    Lambertian LEDs, no visibility; then an einsum with the patterns), eager and torch.compile'd.
The Warp kernels run with visibility off so both sides compute the same thing.

Every benchmark checks that its same-run baseline computes the same thing as the measured path
(`same_work`: elementwise |got - ref| <= rtol |ref| + atol max|ref|, tolerances stated in the JSON) and
reports "passed"; the command exits non-zero when a check fails, so a drifted baseline cannot go unnoticed.
"""
from __future__ import annotations

import math
import platform
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from twin.capture.plan import DEFAULT_FRAMES, DEFAULT_SEED


def random_points(P: int, seed: int = 0, half_size: float = 75.0, plane_z: float = -122.0):
    """Seeded random surface points on the sample plane with the training distribution's ranges."""
    rng = np.random.default_rng(seed)
    pos = np.c_[rng.uniform(-half_size, half_size, (P, 2)), np.full(P, plane_z)]
    n = rng.normal(size=(P, 3)) * 0.3 + [0.0, 0.0, 1.0]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = np.cross(n, rng.normal(size=(P, 3)))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    la, lb = np.log(0.006), np.log(0.5)
    return dict(position=pos, normal=n, tangent=t, rho_d=rng.uniform(0, 1, (P, 3)), rho_s=rng.uniform(0, 10, (P, 3)),
                alpha_x=np.exp(rng.uniform(la, lb, P)), alpha_y=np.exp(rng.uniform(la, lb, P)))


def same_work(name: str, got, ref, *, rtol: float, atol: float = 0.0) -> dict:
    """Whether `got` computes what `ref` does: every element within rtol |ref| + atol max|ref| (and finite).
    The record names the check, its tolerances, the largest relative difference and the worst element's
    share of its bound (<= 1 passes)."""
    got = np.asarray(got, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    rec = {"check": name, "rtol": rtol, "atol_of_max": atol}
    if got.shape != ref.shape:
        return {**rec, "passed": False, "error": f"shape {got.shape} vs {ref.shape}"}
    scale = float(np.abs(ref).max()) if ref.size else 0.0
    err = np.abs(got - ref)
    bound = rtol * np.abs(ref) + atol * scale
    finite = bool(np.all(np.isfinite(got)))
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(err == 0, 0.0, err / bound)
        rel = np.where(err == 0, 0.0, err / np.abs(ref))
    worst = float(share.max()) if share.size else 0.0
    return {**rec, "max_rel_diff": float(rel.max()) if rel.size else 0.0, "worst_share_of_bound": worst,
            "passed": finite and worst <= 1.0}


class PeakDeviceMemory:
    """The peak of a CUDA device's used memory while the block runs, polled every `interval` seconds from NVML
    (torch.cuda.device_memory_used), else from `nvidia-smi`: what Warp's and torch's allocations (and their
    caches) hold together, which no one allocator's counter shows. `peak_mib` stays None where neither answers
    (no GPU, no driver tools).

        with PeakDeviceMemory("cuda:0") as mem:
            ...
        mem.peak_mib
    """

    def __init__(self, device: str, interval: float = 0.1):
        self.device, self.interval, self.peak_mib = str(device), interval, None
        self._stop = None

    def _used_mib(self) -> float | None:
        import subprocess

        import torch

        index = torch.device(self.device).index or 0
        try:
            return torch.cuda.device_memory_used(index) / 2 ** 20
        except Exception:  # noqa: BLE001  (no NVML binding: ask the driver's tool)
            try:
                out = subprocess.run(["nvidia-smi", f"--id={index}", "--query-gpu=memory.used",
                                      "--format=csv,noheader,nounits"], capture_output=True, text=True, timeout=10)
                return float(out.stdout.strip().splitlines()[0])
            except (OSError, ValueError, IndexError, subprocess.SubprocessError):
                return None

    def _poll(self) -> None:
        while not self._stop.is_set():
            used = self._used_mib()
            if used is None:
                return
            self.peak_mib = max(self.peak_mib or 0.0, used)
            self._stop.wait(self.interval)

    def __enter__(self):
        import threading

        if self.device.startswith("cuda"):
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._poll, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc):
        if self._stop is not None:
            self._stop.set()
            self._thread.join()
        return False


def finish_checks(result: dict, checks: list[dict]) -> dict:
    result["checks"] = checks
    result["passed"] = all(c["passed"] for c in checks)
    return result


def bench_exit(res: dict) -> int:
    """A bench command's exit code: 1, naming the failed checks on stderr, when its baseline did not compute
    the same thing (or no check ran)."""
    import sys

    bad = [c["check"] for c in res.get("checks", []) if not c["passed"]]
    if bad or not res.get("passed", False):
        print(f"hemicube: error: the same-work check failed: {bad or 'no checks ran'}", file=sys.stderr)
        return 1
    return 0


def torch_lumitexel(pos, n, t, rd, rs, ax, ay, lpos, lnrm, lint, lexp, cam):
    """Plain batched torch Eq. 1 (physical convention, cosine-power LED profile A = cos^p with the rig's
    intensities I_l, V = 1): (P, L, 3)."""
    import torch

    d = lpos[None] - pos[:, None]  # mm
    r2 = (d * d).sum(-1)
    wi = d / r2.sqrt()[..., None]
    wo = torch.nn.functional.normalize(cam[None] - pos, dim=-1)
    t = torch.nn.functional.normalize(t - (t * n).sum(-1, keepdim=True) * n, dim=-1)
    b = torch.cross(n, t, dim=-1)
    frame = torch.stack([t, b, n], dim=1)  # (P, 3, 3)
    wil = torch.einsum("pij,plj->pli", frame, wi)
    wol = torch.einsum("pij,pj->pi", frame, wo)[:, None]
    h = torch.nn.functional.normalize(wil + wol, dim=-1)
    axx, ayy = ax[:, None], ay[:, None]
    s = (h[..., 0] / axx) ** 2 + (h[..., 1] / ayy) ** 2 + h[..., 2] ** 2
    D = 1.0 / (math.pi * axx * ayy * s * s)

    def g1(v):
        return 2 * v[..., 2] / (v[..., 2] + torch.sqrt((axx * v[..., 0]) ** 2 + (ayy * v[..., 1]) ** 2 + v[..., 2] ** 2))

    G = g1(wil) * g1(wol)
    c = (wil * h).sum(-1).clamp(0, 1)
    F = 0.04 + 0.96 * (1 - c) ** 5
    ci, co = wil[..., 2], wol[..., 2]
    fs = D * F * G / (4 * ci * co)
    f = rd[:, None] / math.pi + rs[:, None] * fs[..., None]
    cos_l = -(wi * lnrm[None]).sum(-1)
    geo = ci.clamp(min=0) * cos_l.clamp(min=0) ** lexp[None] / (r2 * 1e-6)
    valid = (ci > 0) & (co > 0) & (cos_l > 0)
    return torch.where(valid[..., None], f * geo[..., None] * lint[None], torch.zeros_like(f))


def _time(fn, sync, repeats):
    fn()
    sync()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        best = min(best, time.perf_counter() - t0)
    return best


LUMITEXEL_RTOL = 1e-4  # float32 sums of L non-negative terms in different orders: ~sqrt(L) * 2^-24
LUMITEXEL_ATOL = 1e-6  # of the largest value: terms far below it carry float32 evaluation noise only


def bench_lumitexel(rig_name="paper", device="cpu", leds=None, points=4096, patterns=64, repeats=5,
                    compile_torch=True):
    import torch
    import warp as wp

    import twin
    from twin.optics import lumitexel as K
    from twin.optics.emitter import PROFILE_COSINE, PROFILE_MODES
    from twin.optics.inputs import CONVENTIONS, _device_inputs, _led_inputs, make_options
    from twin.optics.forward import TF32_PROJECTION_RTOL, project
    from twin.optics.fused import fused_measurements

    from dataclasses import replace

    rig = twin.load_rig(rig_name)
    if PROFILE_MODES[rig.led_profile] != PROFILE_COSINE:
        raise ValueError(f"bench lumitexel's torch baseline models cosine-power LED profiles only; rig "
                         f"{rig.name!r} has {rig.led_profile!r}")
    # Upper LEDs only: the plain formula has no notion of light arriving through the acrylic from below
    # (a tilted normal would "see" a bottom LED), and the lumitexel of paper §6 is the 12,288 upper LEDs.
    upper = np.flatnonzero(~rig.is_bottom)
    rig = replace(rig, leds=rig.leds.subset(upper[:leds] if leds else upper))
    L, P = rig.num_leds, points
    pts = random_points(P)
    w = np.random.default_rng(1).uniform(0, 1, (patterns, L, 3)).astype(np.float32)
    args = [pts[k] for k in ("position", "normal", "tangent", "rho_d", "rho_s", "alpha_x", "alpha_y")]
    arrays, wpts = _device_inputs(rig, device, "float32", None, *args, np.zeros(P))
    o = make_options(rig, arrays, "physical", "separable", "schlick", 1.5, visibility=False)
    leds_in = _led_inputs(arrays, CONVENTIONS["physical"])
    m = wp.zeros((P, L), dtype=wp.vec3f, device=device)
    out = wp.zeros((P, patterns), dtype=wp.vec3f, device=device)

    def run_mat(fast=False):
        K.materialise(wpts, leds_in, o, m, device, fast)

    def run_mat_fast():
        run_mat(True)

    def run_pointwise():
        wp.launch(K.lumitexel_kernel, dim=(P, L), inputs=[*wpts, *leds_in, o], outputs=[m], device=device)

    def run_fused():
        out.zero_()
        fused_measurements(wpts, leds_in, o, w, out, device)

    sync = lambda: wp.synchronize_device(device)  # noqa: E731
    t_point = _time(run_pointwise, sync, repeats)
    t_mat = _time(run_mat, sync, repeats)
    t_mat_fast = _time(run_mat_fast, sync, repeats)
    t_fused = _time(run_fused, sync, repeats)

    tdev = torch.device("cuda" if str(device).startswith("cuda") else "cpu")
    wt = torch.as_tensor(w, device=tdev)

    def run_mat_projected(fast=False):
        """twin.measurements(method="materialise", fast=fast, tensor_cores=fast): the lumitexels, then
        forward.project (cuBLAS on CUDA)"""
        run_mat(fast)
        sync()  # Warp's stream is not torch's
        return project(wp.to_torch(m), wt, fast)

    def run_mat_tf32():
        return run_mat_projected(True)

    t_mat_proj = _time(run_mat_projected, sync, repeats)
    t_mat_tf32 = _time(run_mat_tf32, sync, repeats)  # on the CPU tensor_cores changes nothing
    T = {k: torch.as_tensor(v, dtype=torch.float32, device=tdev) for k, v in pts.items()}

    def led(a):
        return torch.tensor(np.asarray(a, np.float32), device=tdev)

    lumi_args = (led(rig.led_positions), led(rig.led_normals), led(rig.leds.intensity), led(rig.leds.profile[:, 0]),
                 led(rig.primary.centre))
    chunk = max(1, min(P, int(2e8 // (L * 3 * 8))))  # bound the eager intermediates' memory

    def torch_fused(fn):
        def run():
            outs = []
            for i in range(0, P, chunk):
                s = slice(i, i + chunk)
                lum = fn(T["position"][s], T["normal"][s], T["tangent"][s], T["rho_d"][s], T["rho_s"][s],
                         T["alpha_x"][s], T["alpha_y"][s], *lumi_args)
                outs.append(torch.einsum("klc,plc->pkc", wt, lum))
            return torch.cat(outs)
        return run

    tsync = (lambda: torch.cuda.synchronize()) if tdev.type == "cuda" else (lambda: None)
    result = {
        "benchmark": "lumitexel", "rig": rig_name, "device": str(wp.get_device(device)),
        "device_name": wp.get_device(device).name if tdev.type == "cuda" else platform.processor() or "cpu",
        "leds": L, "points": P, "patterns": patterns, "evaluations": P * L,
        "warp_version": wp.__version__, "torch_version": torch.__version__,
        "warp_materialise_evals_per_s": P * L / t_mat, "warp_materialise_s": t_mat,
        "warp_materialise_kernel": "lumitexel_rows_kernel" if tdev.type == "cuda" else "lumitexel_kernel",
        "warp_materialise_fast_evals_per_s": P * L / t_mat_fast, "warp_materialise_fast_s": t_mat_fast,
        "warp_pointwise_evals_per_s": P * L / t_point, "warp_pointwise_s": t_point,
        "warp_fused_evals_per_s": P * L / t_fused, "warp_fused_s": t_fused,
        "warp_materialise_projected_evals_per_s": P * L / t_mat_proj, "warp_materialise_projected_s": t_mat_proj,
    }
    result.update(warp_materialise_fast_projected_tf32_evals_per_s=P * L / t_mat_tf32,
                  warp_materialise_fast_projected_tf32_s=t_mat_tf32)
    tol = dict(rtol=LUMITEXEL_RTOL, atol=LUMITEXEL_ATOL)
    with torch.no_grad():
        run_eager = torch_fused(torch_lumitexel)
        t_eager = _time(run_eager, tsync, max(1, repeats // 2))
        ref = run_eager().cpu().numpy()
        result["torch_eager_evals_per_s"] = P * L / t_eager
        result["torch_eager_s"] = t_eager
        projected = run_mat_projected().cpu().numpy()
        checks = [same_work("warp_fused_vs_torch_eager", out.numpy(), ref, **tol),
                  same_work("warp_materialise_projected_vs_torch_eager", projected, ref, **tol)]
        fast = run_mat_tf32().cpu().numpy()
        checks.append(same_work("warp_materialise_fast_projected_tf32_vs_torch_eager", fast, ref,
                                rtol=LUMITEXEL_RTOL + TF32_PROJECTION_RTOL, atol=LUMITEXEL_ATOL))
        # the projection alone, against float64 on the same lumitexels, on the first points (float64 copies of
        # all of them would be 19 GB at 65,536 x 12,288)
        n = min(P, 4096)
        exact = torch.einsum("plc,klc->pkc", wp.to_torch(m)[:n].double(), wt.double()).cpu().numpy()
        checks.append(same_work("projection_tf32_vs_float64", fast[:n], exact, rtol=TF32_PROJECTION_RTOL))
        if compile_torch:
            run_comp = torch_fused(torch.compile(torch_lumitexel, dynamic=False))
            t_comp = _time(run_comp, tsync, max(1, repeats // 2))
            result["torch_compile_evals_per_s"] = P * L / t_comp
            result["torch_compile_s"] = t_comp
            checks.append(same_work("torch_compile_vs_torch_eager", run_comp().cpu().numpy(), ref, **tol))
    base = result.get("torch_compile_evals_per_s", result["torch_eager_evals_per_s"])
    result["baseline"] = "torch_compile" if "torch_compile_evals_per_s" in result else "torch_eager"
    result["fused_speedup_vs_baseline"] = result["warp_fused_evals_per_s"] / base
    result["materialise_speedup_vs_baseline"] = result["warp_materialise_evals_per_s"] / base
    return finish_checks(result, checks)


class _LoadLog:
    """A Warp logger that keeps the module-load timings ("Module M load on device D took T ms (compiled)")
    and passes every message on to the logger it replaces."""

    def __init__(self, inner):
        self.inner, self.loads = inner, []

    def info(self, message):
        import re

        m = re.search(r"Module (\S+) .*took ([0-9.]+) ms\s*\((compiled|cached)\)", message)
        if m:
            self.loads.append((m.group(1), m.group(3), float(m.group(2)) / 1e3))

    def debug(self, message):
        pass

    def warning(self, message, category=None, stacklevel=1):
        self.inner.warning(message, category, stacklevel + 1)

    def error(self, message):
        self.inner.error(message)


@contextmanager
def _module_loads():
    """[(module, "compiled" | "cached", seconds)] of the Warp modules loaded inside the block: on a cold
    kernel cache, the compile times."""
    import warp as wp

    log = _LoadLog(wp.get_logger())
    level = wp.config.log_level
    wp.set_logger(log)
    wp.config.log_level = wp.LOG_INFO
    try:
        yield log.loads
    finally:
        wp.config.log_level = level
        wp.set_logger(log.inner)


CAPTURE_RENDER_RTOL = 1e-5  # the device render vs the float32 fused kernel: float32 sums in other orders
CAPTURE_RENDER_ATOL = 1e-6  # of the image's largest value


def bench_capture(rig_name="paper", device="cuda", sample="ramps", resolution=1024, seed=DEFAULT_SEED, scale=1.0,
                  check_rows=8, output=None, frames=DEFAULT_FRAMES):
    """Seconds for the whole capture plan's simulation on `device` (every photo of both views; no
    extrapolation), by stage, with the production code (twin.capture.runner.photos): pixel tracing, the
    render of every pattern, the sensor (exposure bracket and raw frames), the HDR merge, and the download
    of the finished HDR images to the host (files excluded: `hemicube capture` then writes and checksums them;
    with --raw it also downloads and packs the raw frames). `output`: then also the real
    `hemicube capture` into that folder, files written, timed whole. A warm-up on two rows of a camera
    comes first (on a cold Warp cache it is the kernels' compilation).

    Same work: on `check_rows` rows of every traced view, the trace against the numpy trace, and the render
    of every pattern against the public forward model's fused float32 kernel with numpy finishing
    (twin.camera.imaging's oracles); the first photo's HDR merge against the numpy merge."""
    import warp as wp

    import twin
    from twin.camera.hdr import merge_hdr_numpy
    from twin.camera.imaging import render_device, render_reference, trace_pixels, trace_pixels_numpy
    from twin.camera.sensor import raw_frame, sensor_consts
    from twin.capture.plan import build_patterns, check_frames, paper_plan
    from twin.capture.runner import HostCopies, open_backends, photos
    from twin.materials.samples import load_sample
    from twin.optics.inputs import check_device

    from collections import defaultdict
    from dataclasses import replace

    device = check_device(device)
    frames = check_frames(frames)
    rig = twin.load_rig(rig_name)
    if scale != 1.0:
        rig = replace(rig, cameras={n: c.resized(scale) for n, c in rig.cameras.items()})
    maps = load_sample(sample, resolution=resolution)
    patterns = build_patterns(rig)
    plan = paper_plan(rig, patterns)
    index = {n: k for k, n in enumerate(patterns.names)}
    need = {}  # (scene, camera) -> the plan's pattern indices there
    for p in plan:
        need.setdefault((p.sample, p.camera), set()).add(index[p.pattern])
    need = {key: sorted(ks) for key, ks in need.items()}
    dev = wp.get_device(device)
    res = {"benchmark": "capture", "rig": rig.name, "device": str(dev),
           "device_name": dev.name if dev.is_cuda else platform.processor() or "cpu", "sample": sample,
           "sample_resolution": resolution, "camera_scale": scale, "photos": len(plan), "frames_per_exposure": frames,
           "warp_version": wp.__version__,
           "cameras": {n: [c.width, c.height] for n, c in rig.cameras.items()}}
    seconds = defaultdict(float)

    @contextmanager
    def stage(name):
        wp.synchronize_device(dev)
        t0 = time.perf_counter()
        yield
        wp.synchronize_device(dev)
        seconds[name] += time.perf_counter() - t0

    with stage("warmup"), _module_loads() as loads:  # every kernel once, on two rows
        cam0 = next(iter(rig.cameras))
        s = trace_pixels(rig, cam0, maps, device=device, rows=(0, 2))
        w = patterns.weights[[index["uniform"]] + ([index["bottom"]] if "bottom" in index else [])]
        img = render_device(rig, cam0, s, w, device=device)
        raws = wp.empty((1, 2, rig.camera(cam0).width), dtype=wp.uint16, device=dev)
        raw_frame(img[0], sensor_consts(rig.camera(cam0).sensor, exposure_s=1e-3, seed=0, frame=0,
                                        camera_key="warmup"), raws[0])
        from twin.camera.hdr import merge_hdr_device

        merge_hdr_device(raws, [1e-3], rig.camera(cam0).sensor)
    res["warp_modules_compiled"] = [m for m, how, _ in loads if how == "compiled"]
    res["warp_compile_s"] = sum(t for _, how, t in loads if how == "compiled")
    res["warp_module_load_s"] = sum(t for _, _, t in loads)
    checked = None
    host = HostCopies()
    with open_backends(rig, maps, "sim", seed, device) as sims:
        with stage("trace"):
            surfaces = {key: sims[key[0]].surfaces(key[1]) for key in need}
        for photo, raws, hdr, record in photos(rig, sims, patterns, plan, device, stage, frames=frames):
            with stage("download"):  # what `hemicube capture` (without --raw) hands to its file writers
                (radiance,) = host(0, hdr["radiance"])
            if checked is None:
                checked = photo, record, raws.numpy().copy(), radiance.copy()
    res["rays"] = {f"{k}/{c}": int(s.kind.shape[0]) for (k, c), s in surfaces.items()}
    res["seconds"] = dict(seconds)
    res["total_s_files_excluded"] = sum(v for k, v in seconds.items() if k != "warmup")

    checks = []
    for kind, cam in surfaces:
        H = rig.camera(cam).height
        rows = (max(0, H // 2 - check_rows // 2), min(H, H // 2 - check_rows // 2 + check_rows))
        m = maps if kind == "sample" else None
        ours = trace_pixels(rig, cam, m, device=device, rows=rows).host()
        ref = trace_pixels_numpy(rig, cam, m, rows=np.arange(*rows))
        checks.append(same_work(f"trace_kind_{kind}_{cam}", ours.kind, ref.kind, rtol=0.0))
        for f in ("position", "normal", "rho_d", "alpha_x"):
            checks.append(same_work(f"trace_{f}_{kind}_{cam}", getattr(ours, f), getattr(ref, f).astype(np.float32),
                                    rtol=2.0 ** -23))  # float32 rounding of the numpy float64 values, 1 ulp
        w = patterns.weights[need[(kind, cam)]]
        checks.append(same_work(f"render_{kind}_{cam}", render_device(rig, cam, ours, w, device=device).numpy(),
                                render_reference(rig, cam, ours, w, device=device), rtol=CAPTURE_RENDER_RTOL,
                                atol=CAPTURE_RENDER_ATOL))
    photo, record, raws_host, rad_host = checked
    ref = merge_hdr_numpy(list(raws_host), record["exposures_s"], rig.camera(photo.camera).sensor)
    checks.append(same_work("hdr_merge_first_photo", rad_host, ref.radiance, rtol=0.0))

    if output is not None:
        from twin.capture.runner import capture

        t0 = time.perf_counter()
        capture(rig, sample, output, seed=seed, device=device, resolution=resolution, progress=False, frames=frames)
        res["total_s_files_written"] = time.perf_counter() - t0
        res["output_bytes"] = sum(f.stat().st_size for f in Path(output).rglob("*") if f.is_file())
    return finish_checks(res, checks)

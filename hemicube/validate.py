"""`hemicube validate`: the main job. Simulate, reconstruct, score.

1. checks of the rig model and the forward model (twin.checks), each saying what it compared, its worst
   error and its threshold (against the released device's files where ../shared/reference is present);
2. end to end: a virtual capture of the sample (`twin.capture.runner`, seed 1) -> the reconstruction pipeline
   (`reconstruction.pipeline`: alignment, extraction, decode with the shipped network, three-pass
   fine-tuning, GGX fitting) -> the score against the capture's ground truth
   (`reconstruction.evaluation.validation`), with the thresholds of `reconstruction.evaluation.validation.thresholds_for` (stated
   there and in docs/accuracy.md).
Writes OUTPUT/capture, OUTPUT/reconstruction and OUTPUT/report (report.md, metrics.json, images/); prints a
metrics table. Exit code non-zero when a check or a threshold fails. Without -o, OUTPUT is
hemicube-validate/<rig>_<sample>_seed<seed>, so that runs on different samples never share a capture.

`--suite [NAMES]` runs step 2 on every named sample (default: the material suite,
twin.materials.samples.SUITE), as many at a time as there are cores, each in its own process and folder
(OUTPUT/<sample>/), then prints one table (sample x metric, pass/fail) and writes OUTPUT/report/ with every
sample's map panels side by side (truth | reconstruction | error). Progress goes to stderr.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from pathlib import Path

from twin.capture.plan import DEFAULT_FRAMES
from twin.capture.session import CAPTURE_FOLDER
from twin.outputs import Kind, claim_output

from reconstruction.output import RECONSTRUCTION_FOLDER
from reconstruction.evaluation.novel_views import summary_line

DEFAULT_ROOT = Path("hemicube-validate")
# OUTPUT, resumed (twin.outputs): its capture or reconstruction says what it is; a suite's are one folder deeper
_PARTS = tuple(f"{part}/{marker}" for part, kind in (("capture", CAPTURE_FOLDER),
                                                     ("reconstruction", RECONSTRUCTION_FOLDER))
               for marker in kind.markers)
VALIDATE_FOLDER = Kind("a validate folder", _PARTS)
SUITE_FOLDER = Kind("a validate --suite folder", tuple(f"*/{m}" for m in _PARTS))


def _claim(out: Path, kind: Kind, rig: str, samples) -> None:
    """OUTPUT checked before the checks and the captures (twin.outputs): of its own kind or new, holding none of
    the folders read (a rig folder, a sample's maps)."""
    claim_output(out, kind, [("the rig folder", rig)] + [("the maps of sample " + str(s), s) for s in samples])


def _sample_name(sample: str) -> str:
    """A folder-safe name of a built-in sample or a map folder."""
    name = Path(sample).name if os.sep in str(sample) or Path(sample).is_dir() else str(sample)
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "sample"


def end_to_end(rig_obj, sample: str, device: str, output: Path, resolution: int | None, seed: int,
               progress: bool, network: str = "pretrained", learned=None,
               frames: int = DEFAULT_FRAMES) -> tuple[dict, list, dict]:
    """Simulate a capture, reconstruct it, score it: (metrics, threshold rows, report paths). `learned` (a
    PatternSet of 2K frames) and `network` (a `hemicube train` run folder) capture and decode with another
    network's patterns (a capture design, hemicube.design) instead of the rig's own; `frames`: each exposure
    taken that many times (twin.capture.plan.bracket_frames)."""
    from dataclasses import replace

    from reconstruction.evaluation.metrics import check
    from reconstruction.pipeline import ReconstructConfig, reconstruct
    from reconstruction.evaluation.report import write_report
    from reconstruction.evaluation.validation import evaluate, thresholds_for
    from twin.capture.runner import SAMPLE_RESOLUTION, capture

    resolution = resolution or ReconstructConfig.resolution
    # the sample's maps at least as fine as the texture grid, so that a fine grid never scores upsampled maps
    # (the paper's latents and maps are both 1024^2: reference §8)
    cap = capture(rig_obj, sample, output / "capture", seed=seed, device=device, progress=progress, learned=learned,
                  resolution=max(SAMPLE_RESOLUTION, resolution), frames=frames)
    config = replace(ReconstructConfig(), resolution=resolution, device=device, network=str(network))
    recon = reconstruct(cap, output / "reconstruction", config, progress=progress, rig=rig_obj)
    metrics, panels = evaluate(cap, recon, rig_obj, device=device)
    thresholds = thresholds_for(rig_obj.name, resolution, str(sample))
    rows = check(metrics, thresholds)
    notes = [f"rig {rig_obj.name!r}, sample {sample!r}, seed {seed}, {frames} frame(s) an exposure, device {device}, "
             f"texture grid {resolution}^2 over {recon.grid.size_mm:.1f} mm, line {recon.holdout_line} held out of fine-tuning",
             "renders compare texel values on the texture grid (network units); 'truth_maps' renders the true maps "
             "the same way: the ceiling that the photo's noise and pixel footprint allow"]
    check_ = recon.alignment.info.get("check")
    if check_ is not None:
        notes.append("alignment check without ground truth (what a real capture runs): " + (
            f"the views agree to {check_['median_shift_px']:.2f} px over {check_['tiles_used']} tiles (flagged above "
            f"{check_['flag_px']} px)" + (" FLAGGED" if check_["flagged"] else "") if check_["verified"] else
            f"not verified: {check_['tiles_used']} of {check_['tiles']} tiles have texture of the sample's own"))
    if not thresholds:
        notes.append(f"no thresholds are set for rig {rig_obj.name!r}: the numbers are reported, not checked")
    paths = write_report(output / "report", title=f"hemicube validate: {rig_obj.name} / {sample}",
                         metrics=metrics, checks=rows, panels=panels, notes=notes)
    return metrics, rows, paths


def _self_checks(rig_obj, device: str):
    from twin.checks import forward_checks, reference_checks, reference_dir, rig_checks

    ref = reference_dir()
    checks = rig_checks(rig_obj)
    if ref is not None:
        checks += reference_checks(ref)
    return checks + forward_checks(rig_obj, device, ref), ref


def _print_checks(checks) -> None:
    w = max(len(c.name) for c in checks)
    for c in checks:
        print(f"  [{'PASS' if c.passed else 'FAIL'}] {c.name:<{w}}  worst {c.worst:.3g} {c.unit} "
              f"(threshold {c.threshold:g})  -- {c.compared}")


# a capture whose render evaluates more LED responses than this gets a timed estimate first on the CPU (the
# mini rig's plan is ~10^9: minutes; the paper rig's ~3 x 10^11: hours)
ESTIMATE_ABOVE = 1e10
TOO_LONG_S = 1800  # on the CPU, refuse (unless anyway) a capture estimated to take longer than this


def capture_evaluations(rig_obj, maps) -> float:
    """LED responses the capture's render evaluates: every sub-pixel ray of every camera, on the sample and on
    the empty board, times the rig's LEDs (an upper bound: each pattern group evaluates only its lit LEDs)."""
    from twin.camera.imaging import _supersampling

    rays = sum(c.width * c.height * (_supersampling(rig_obj, n, maps, None) ** 2 + 1)
               for n, c in rig_obj.cameras.items())
    return float(rays) * rig_obj.num_leds


def cpu_capture_estimate(rig_obj, maps, rows: int = 1) -> dict:
    """Seconds the capture's render would take on this CPU, from a timed render of `rows` rows of the primary
    camera with every pattern of the plan, scaled by the rays (sample and empty board, all cameras). The
    sensor and HDR stages and the files add to it; the reconstruction comes on top."""
    from twin.camera.imaging import _supersampling, render, trace_pixels
    from twin.capture.plan import build_patterns

    name, cam = next(iter(rig_obj.cameras.items()))
    mid = cam.height // 2
    weights = build_patterns(rig_obj).weights
    surfaces = trace_pixels(rig_obj, name, maps, rows=(mid, mid + rows))
    render(rig_obj, name, trace_pixels(rig_obj, name, maps, rows=(0, 1)), weights[:1])  # kernels loaded, not timed
    t = time.perf_counter()
    render(rig_obj, name, surfaces, weights)
    timed = time.perf_counter() - t
    total = capture_evaluations(rig_obj, maps)
    share = rows * cam.width * _supersampling(rig_obj, name, maps, None) ** 2 * rig_obj.num_leds / total
    return {"render_s": timed / share, "timed_s": timed, "evaluations": total}


def run_validation(rig="mini", sample="ramps", device="cpu", as_json=False, output=None,
                   resolution: int | None = None, seed: int = 1, progress: bool = True, anyway: bool = False,
                   frames: int = DEFAULT_FRAMES, junit=None) -> int:
    """The main job: rig and forward-model checks, then capture -> reconstruct -> score (see the module
    docstring). Exit code 0 when every check and every threshold passes. On the CPU, a rig whose capture
    would take hours (the paper rig) is refused with a timed estimate first, unless `anyway`. `junit`: a file to
    write the checks and thresholds to as JUnit XML (hemicube.junit).

    rig         a built-in rig's name or a rig folder (twin.load_rig; lengths in mm)
    sample      a built-in sample's name, "NAME@SEED" or a map folder (twin.materials.samples.load_sample)
    device      where the capture and the reconstruction run: "cpu", "cuda" or "cuda:N"
    output      the folder for capture/, reconstruction/ and report/
                (default: hemicube-validate/RIG_SAMPLE_seedSEED_xFRAMES)
    resolution  texels a side of the reconstruction's texture grid (default: ReconstructConfig's, 48)
    seed        the capture's noise; frames: each exposure taken that many times (DEFAULT_FRAMES = 4)
    as_json     print the report as JSON (metrics in the units their names end in: _px pixels, _deg degrees,
                _pct %, _db dB, _s seconds, _mm mm) instead of the table"""
    import twin
    from reconstruction.evaluation.metrics import format_table, to_jsonable
    from twin.capture.plan import check_frames
    from twin.capture.runner import SAMPLE_RESOLUTION
    from twin.materials.samples import load_sample

    rig_obj = twin.load_rig(rig)
    check_frames(frames)  # before the checks and the folder: a bad count is one line, nothing written
    out = Path(output) if output else DEFAULT_ROOT / f"{rig_obj.name}_{_sample_name(sample)}_seed{seed}{_x(frames)}"
    _claim(out, VALIDATE_FOLDER, rig, [sample])
    if device == "cpu" and not anyway:
        maps = load_sample(sample, resolution=SAMPLE_RESOLUTION)
        if capture_evaluations(rig_obj, maps) > ESTIMATE_ABOVE and \
                (est := cpu_capture_estimate(rig_obj, maps))["render_s"] > TOO_LONG_S:
            raise ValueError(
                f"validate --rig {rig_obj.name} on the CPU: its capture alone would take about "
                f"{est['render_s'] / 3600:.1f} h here ({est['evaluations']:.1e} LED evaluations; one row took "
                f"{est['timed_s']:.1f} s), before the reconstruction's hours; use --device cuda, or --anyway to run it")
    checks, ref = _self_checks(rig_obj, device)
    metrics, rows, paths = end_to_end(rig_obj, sample, device, out, resolution, seed, progress and not as_json,
                                      frames=frames)
    ok = all(c.passed for c in checks) and all(r["passed"] for r in rows)
    report = {
        "rig": rig_obj.name, "sample": sample, "device": device, "passed": ok,
        "reference_data": str(ref) if ref else None,
        "checks": [{**c.__dict__, "passed": c.passed} for c in checks],
        "thresholds": rows, "metrics": metrics, "report": paths,
    }
    if junit is not None:
        from hemicube.junit import check_cases, threshold_cases, write_junit

        write_junit(junit, [(f"hemicube validate {rig_obj.name}/{sample}",
                             check_cases(checks) + threshold_cases(rows))])
    if as_json:  # strict JSON: paths as strings, NaN as null (reconstruction.evaluation.metrics.to_jsonable)
        print(json.dumps(to_jsonable(report), indent=2, allow_nan=False))
        return 0 if ok else 1
    print(f"hemicube validate: rig {rig_obj.name!r} ({rig_obj.num_leds} LEDs), sample {sample!r}, device {device}")
    if ref is None:
        print("  (reference data not found: set HEMICUBE_REFERENCE to the OpenSVBRDF lightstage folder to add "
              "the checks against the released device)")
    _print_checks(checks)
    print(format_table(rows))
    print("  " + summary_line(metrics["novel"]))
    t = metrics["timings_s"]
    print("  seconds: " + ", ".join(f"{k[:-2]} {v:.1f}" for k, v in t.items()))
    print(f"  report: {paths.get('report_md', out / 'report')}")
    print("result:", "all checks passed" if ok else "FAILED")
    return 0 if ok else 1


# --- the suite ------------------------------------------------------------------------------------------
def _one_thread() -> None:
    """Suite workers share the cores: one torch thread each (oversubscribed threads cost up to 10x)."""
    import torch

    torch.set_num_threads(1)


def _x(frames: int) -> str:
    """The default folders' mark of frames an exposure other than one (a folder holds one capture, and the folders
    made before frame averaging hold one-frame captures)."""
    return "" if frames == 1 else f"_x{frames}"


def suite_folder_name(rig: str, names, seed: int, frames: int) -> str:
    """The default folder of a suite run: the whole suite's is suite_RIG_seedSEED; a run of other samples adds their
    names (or, past 60 characters, their count and a digest of the list), so that two runs never share a folder."""
    from twin.materials.samples import SUITE

    base = f"suite_{rig}_seed{seed}{_x(frames)}"
    if list(names) == list(SUITE):
        return base
    joined = "+".join(_sample_name(s) for s in names)
    if len(joined) > 60:
        joined = f"{len(names)}samples_" + hashlib.sha256("\n".join(map(str, names)).encode()).hexdigest()[:8]
    return f"{base}_{joined}"


def _suite_member(rig: str, sample: str, device: str, output: str, resolution, seed: int,
                  frames: int = DEFAULT_FRAMES) -> dict:
    """One suite sample in its own process: capture -> reconstruct -> score into `output`."""
    import twin

    t0 = time.perf_counter()
    try:
        metrics, rows, paths = end_to_end(twin.load_rig(rig), sample, device, Path(output), resolution, seed, False,
                                          frames=frames)
    except Exception as e:  # noqa: BLE001 - one sample's failure is reported in the table, not fatal to the rest
        return {"sample": sample, "passed": False, "error": f"{type(e).__name__}: {e}", "rows": [],
                "seconds": time.perf_counter() - t0}
    return {"sample": sample, "passed": all(r["passed"] for r in rows), "rows": rows, "metrics": metrics,
            "images": {k: str(v) for k, v in paths["images"].items()}, "seconds": time.perf_counter() - t0}


def suite_results(names=None, rig="mini", device="cpu", output=None, resolution: int | None = None, seed: int = 1,
                  jobs: int | None = None, frames: int = DEFAULT_FRAMES) -> dict:
    """Run the suite (module docstring) and write its report: {"rig", "device", "checks", "samples" (one result
    per name, in order), "report" (its folder), "passed"}."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    import twin
    from twin.capture.plan import check_frames
    from twin.materials.samples import SUITE, check_sample

    names = list(names or SUITE)
    for s in names:  # one line before any work, not an error per sample
        check_sample(s)
    rig_obj = twin.load_rig(rig)
    check_frames(frames)
    out = Path(output) if output else DEFAULT_ROOT / suite_folder_name(rig_obj.name, names, seed, frames)
    _claim(out, SUITE_FOLDER, rig, names)
    checks, _ = _self_checks(rig_obj, device)
    jobs = max(1, min(jobs or os.cpu_count() or 1, len(names)))
    if str(device).startswith("cuda"):
        jobs = 1  # one GPU: the samples queue on it
    print(f"[suite] {len(names)} samples on rig {rig_obj.name!r}, {jobs} at a time -> {out}", file=sys.stderr)
    results = {}
    t0 = time.perf_counter()
    # spawn, not fork: each worker initialises its own Warp and torch
    with ProcessPoolExecutor(jobs, mp_context=mp.get_context("spawn"), initializer=_one_thread) as pool:
        futures = {pool.submit(_suite_member, rig, s, device, str(out / _sample_name(s)), resolution, seed, frames): s
                   for s in names}
        for f in as_completed(futures):
            r = f.result()
            results[r["sample"]] = r
            state = "PASS" if r["passed"] else ("ERROR " + r["error"] if "error" in r else "FAIL")
            print(f"[suite] {len(results)}/{len(names)} {r['sample']}: {state} ({r['seconds']:.0f} s, "
                  f"{time.perf_counter() - t0:.0f} s elapsed)", file=sys.stderr, flush=True)
    ordered = [results[s] for s in names]
    report = write_suite_report(out / "report", rig_obj.name, ordered, checks)
    ok = all(c.passed for c in checks) and all(r["passed"] for r in ordered)
    return {"rig": rig_obj.name, "device": device, "checks": checks, "samples": ordered, "report": report,
            "passed": ok}


def run_suite(names=None, rig="mini", device="cpu", output=None, resolution: int | None = None, seed: int = 1,
              jobs: int | None = None, as_json=False, frames: int = DEFAULT_FRAMES, junit=None) -> int:
    """`hemicube validate --suite [NAMES]` (module docstring). Exit code 0 when every check and every
    threshold of every sample passes. `junit`: a file for the JUnit XML (hemicube.junit): the checks, then one test
    suite a sample.

    names is a list of sample names or map folders (default: the material suite, twin.materials.samples.SUITE);
    rig, device, resolution (texels a side), seed, frames and as_json are run_validation's. jobs: samples at once
    in their own processes (default: the CPU cores; 1 on a GPU). output: the folder, one sub-folder a sample
    (default: hemicube-validate/suite_RIG_seedSEED_xFRAMES...). The table's and the JSON's figures are in the units
    their names end in (_px pixels, _deg degrees, _pct %, _db dB, _s seconds)."""
    res = suite_results(names, rig, device, output, resolution, seed, jobs, frames)
    checks, ordered, report, ok = res["checks"], res["samples"], res["report"], res["passed"]
    names = [r["sample"] for r in ordered]
    if junit is not None:
        from hemicube.junit import write_junit

        write_junit(junit, suite_junit(res))
    if as_json:
        from reconstruction.evaluation.metrics import to_jsonable

        print(json.dumps(to_jsonable({"rig": res["rig"], "device": device, "passed": ok, "report": report,
                                      "checks": [{**c.__dict__, "passed": c.passed} for c in checks],
                                      "samples": [_without_pairs(r) for r in ordered]}), indent=2, allow_nan=False))
        return 0 if ok else 1
    print(f"hemicube validate --suite: rig {res['rig']!r}, {len(names)} samples, device {device}")
    _print_checks(checks)
    print(suite_table(ordered))
    for r in ordered:  # a sample that misses a novel-view goal names its worst view and light
        if any(row["metric"].startswith("novel.") and not row["passed"] for row in r["rows"]):
            print(f"  {r['sample']}: {summary_line(r['metrics']['novel'])}")
    print(f"  report: {report}")
    print("result:", "all samples passed" if ok else "FAILED")
    return 0 if ok else 1


def suite_junit(res: dict) -> list:
    """A suite run's (suite_results) test suites for hemicube.junit: the checks, then one a sample (its thresholds, or
    the error that stopped it)."""
    from hemicube.junit import check_cases, threshold_cases

    return [(f"hemicube validate --suite {res['rig']}: checks", check_cases(res["checks"]))] + [
        (f"hemicube validate {res['rig']}/{r['sample']}",
         [{"name": "run", "passed": False, "error": r["error"]}] if "error" in r else threshold_cases(r["rows"]))
        for r in res["samples"]]


def _without_pairs(result: dict) -> dict:
    """A suite sample's result without its report images and its novel views' per-pair rows."""
    out = {k: v for k, v in result.items() if k != "images"}
    if "novel" in out.get("metrics", {}):
        out["metrics"] = {**out["metrics"], "novel": {k: v for k, v in out["metrics"]["novel"].items()
                                                      if k != "pairs"}}
    return out


def suite_table(results: list[dict]) -> str:
    """One row per sample, one column per thresholded metric: the value, with '!' where it misses."""
    from reconstruction.evaluation.metrics import _fmt_value

    metrics = list(dict.fromkeys(r["metric"] for res in results for r in res["rows"]))
    short = [m.replace("maps.", "").replace("_pct.median", "%").replace("_deg.median", "°")
             .replace(".median_px", " px").replace("render.", "") for m in metrics]
    head = ["sample"] + short + ["result"]
    body = []
    for res in results:
        by = {r["metric"]: r for r in res["rows"]}
        cells = [(_fmt_value(by[m]["value"]) + ("" if by[m]["passed"] else "!")) if m in by else "-" for m in metrics]
        body.append([res["sample"]] + cells + ["PASS" if res["passed"] else res.get("error", "FAIL")[:40]])
    widths = [max(len(str(row[i])) for row in [head] + body) for i in range(len(head))]
    lines = ["  ".join(str(c).rjust(w) if i else str(c).ljust(w) for i, (c, w) in enumerate(zip(row, widths)))
             for row in [head] + body]
    return "\n".join([lines[0], "-" * len(lines[0])] + lines[1:] + ["('!' marks a value that misses its threshold)"])


def write_suite_report(out_dir: Path, rig_name: str, results: list[dict], checks) -> Path:
    """OUTPUT/report/: report.md (the table, then each sample's map panels side by side), metrics.json,
    images/<sample>_<panel>.png. Written whole (twin.atomic.atomic_folder)."""
    import shutil

    from reconstruction.evaluation.metrics import _fmt_value, to_jsonable
    from twin.atomic import atomic_folder, write_bytes_atomic

    ok = all(c.passed for c in checks) and all(r["passed"] for r in results)
    md = [f"# hemicube validate --suite: {rig_name}", "",
          f"**Result: {'PASS' if ok else 'FAIL'}** ({sum(r['passed'] for r in results)} of {len(results)} "
          "samples meet every threshold).", "", "```text", suite_table(results), "```", ""]
    for res in results:
        md += [f"## {res['sample']}: {'PASS' if res['passed'] else 'FAIL'} ({res['seconds']:.0f} s)", ""]
        if "error" in res:
            md += [f"Error: `{res['error']}`", ""]
        md += [f"- `{r['metric']}` = {_fmt_value(r['value'])} ({r['op']} {r['threshold']:g}: "
               f"{'pass' if r['passed'] else '**FAIL**'}; {r.get('why', '')})" for r in res["rows"]]
        if "novel" in res.get("metrics", {}):
            md += [f"- {summary_line(res['metrics']['novel'])}"]
        md += [""] + [f"![{res['sample']} {name}](images/{res['sample']}_{name}.png)"
                      for name in res.get("images", {}) if not name.startswith("heldout")] + [""]
    # each sample's 560 novel-view pairs stay in its own report's metrics.json
    doc = to_jsonable({"rig": rig_name, "passed": ok, "samples": [_without_pairs(r) for r in results]})
    with atomic_folder(out_dir, overwrite=True) as tmp:
        (tmp / "images").mkdir()
        for res in results:
            for name, path in res.get("images", {}).items():
                if not name.startswith("heldout"):
                    shutil.copyfile(path, tmp / "images" / f"{res['sample']}_{name}.png")
        write_bytes_atomic(tmp / "metrics.json", (json.dumps(doc, indent=2, allow_nan=False) + "\n").encode())
        write_bytes_atomic(tmp / "report.md", "\n".join(md).encode())
    return out_dir / "report.md"

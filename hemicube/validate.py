"""`hemicube validate`: the main job. Simulate, reconstruct, score.

1. checks of the rig model and the forward model (twin.checks), each saying what it compared, its worst
   error and its threshold (against the released device's files where ../shared/reference is present);
2. end to end: a virtual capture of the sample (`twin.capture.runner`, seed 1) -> the reconstruction pipeline
   (`reconstruction.pipeline`: alignment, extraction, decode with the shipped network, three-pass
   fine-tuning, GGX fitting) -> the score against the capture's ground truth
   (`reconstruction.validation`), with the rig's thresholds (stated there and in docs/accuracy.md).
Writes OUTPUT/capture, OUTPUT/reconstruction and OUTPUT/report (report.md, metrics.json, images/); prints a
metrics table. Exit code non-zero when a check or a threshold fails.
"""
from __future__ import annotations

import json
from pathlib import Path

def end_to_end(rig_obj, sample: str, device: str, output: Path, resolution: int, seed: int,
               progress: bool) -> tuple[dict, list, dict]:
    """Simulate a capture, reconstruct it, score it: (metrics, threshold rows, report paths)."""
    from dataclasses import replace

    from reconstruction.pipeline import ReconstructConfig, reconstruct
    from reconstruction.metrics import check
    from reconstruction.report import write_report
    from reconstruction.validation import evaluate, thresholds_for

    from twin.capture.runner import capture

    cap = capture(rig_obj, sample, output / "capture", seed=seed, device=device, progress=progress)
    config = replace(ReconstructConfig(), resolution=resolution, device=device)
    recon = reconstruct(cap, output / "reconstruction", config, progress=progress, rig=rig_obj)
    metrics, panels = evaluate(cap, recon, rig_obj, device=device)
    rows = check(metrics, thresholds_for(rig_obj.name) if resolution == ReconstructConfig.resolution else [])
    notes = [f"rig {rig_obj.name!r}, sample {sample!r}, seed {seed}, device {device}, texture grid "
             f"{resolution}^2 over {recon.grid.size_mm:.1f} mm, line {recon.holdout_line} held out of fine-tuning",
             "renders compare texel values on the texture grid (network units); 'truth_maps' renders the true maps "
             "the same way: the ceiling that the photo's noise and pixel footprint allow"]
    if resolution != ReconstructConfig.resolution:
        notes.append(f"thresholds are set for the default grid ({ReconstructConfig.resolution}^2); none applied")
    paths = write_report(output / "report", title=f"hemicube validate: {rig_obj.name} / {sample}",
                         metrics=metrics, checks=rows, panels=panels, notes=notes)
    return metrics, rows, paths


def run_validation(rig="mini", sample="ramps", device="cpu", as_json=False, output="hemicube-validate",
                   resolution: int | None = None, seed: int = 1, progress: bool = True) -> int:
    """The main job: rig and forward-model checks, then capture -> reconstruct -> score (see the module
    docstring). Exit code 0 when every check and every threshold passes."""
    import twin
    from reconstruction.metrics import format_table
    from reconstruction.pipeline import ReconstructConfig
    from twin.checks import forward_checks, reference_checks, reference_dir, rig_checks

    rig_obj = twin.load_rig(rig)
    ref = reference_dir()
    checks = rig_checks(rig_obj)
    if ref is not None:
        checks += reference_checks(ref)
    checks += forward_checks(rig_obj, device, ref)
    out = Path(output)
    metrics, rows, paths = end_to_end(rig_obj, sample, device, out, resolution or ReconstructConfig.resolution,
                                      seed, progress and not as_json)
    ok = all(c.passed for c in checks) and all(r["passed"] for r in rows)
    report = {
        "rig": rig_obj.name, "sample": sample, "device": device, "passed": ok,
        "reference_data": str(ref) if ref else None,
        "checks": [{**c.__dict__, "passed": c.passed} for c in checks],
        "thresholds": rows, "metrics": metrics, "report": {k: str(v) for k, v in paths.items()},
    }
    if as_json:
        print(json.dumps(report, indent=2, default=lambda o: None))
        return 0 if ok else 1
    print(f"hemicube validate: rig {rig_obj.name!r} ({rig_obj.num_leds} LEDs), sample {sample!r}, device {device}")
    if ref is None:
        print("  (reference data not found: set HEMICUBE_REFERENCE to the OpenSVBRDF lightstage folder to add "
              "the checks against the released device)")
    w = max(len(c.name) for c in checks)
    for c in checks:
        print(f"  [{'PASS' if c.passed else 'FAIL'}] {c.name:<{w}}  worst {c.worst:.3g} {c.unit} "
              f"(threshold {c.threshold:g})  -- {c.compared}")
    print(format_table(rows))
    t = metrics["timings_s"]
    print("  seconds: " + ", ".join(f"{k[:-2]} {v:.1f}" for k, v in t.items()))
    print(f"  report: {paths.get('report', out / 'report')}")
    print("result:", "all checks passed" if ok else "FAILED")
    return 0 if ok else 1

"""Issue #14 (docs/accuracy.md, step 12): paper compositions that no test uses, with and without the refit of the
texels next to a brighter highlight (ReconstructConfig.spill_ratio), end to end as `hemicube validate` runs them
(mini rig, capture seed 1, CPU).

    python docs/bench/spill_refit_unseen_2026-11-27.py SAMPLE OUT RATIO      (RATIO: 4, or none)

Prints the goal rows as JSON. A record of how the numbers were measured, not part of the pipeline.
"""
import json, os, sys, time
from dataclasses import replace
from pathlib import Path
import torch
torch.set_num_threads(1)
import twin
import reconstruction.pipeline as P
sample, out, ratio = sys.argv[1], Path(sys.argv[2]), sys.argv[3]
real = P.reconstruct
P.reconstruct = lambda cap, o, config, **k: real(cap, o, replace(config, spill_ratio=None if ratio == "none" else float(ratio)), **k)
from hemicube.validate import end_to_end
t = time.time()
metrics, rows, _ = end_to_end(twin.load_rig("mini"), sample, "cpu", out, None, 1, False)
print(json.dumps({"sample": sample, "spill_ratio": ratio, "s": round(time.time() - t, 1),
                  "rows": [(r["metric"], round(float(r["value"]), 4), r["passed"]) for r in rows]}), flush=True)

"""`hemicube validate --sample NAME --resolution R` (mini rig, CPU, capture seed 1) with the extraction's footprint
forced (ReconstructConfig.footprint; validate has no option for it), in this process, as run for docs/accuracy.md:

    python docs/bench/footprint_cell_2026-11-26.py point 24 OUT satin wood fabric paper > point.json
    python docs/bench/footprint_cell_2026-11-26.py cell 24 OUT satin wood fabric paper > cell.json

(merged into footprint_cell_mini_cpu_24_2026-11-26.json). A record of how the numbers were measured."""
import json, sys
from pathlib import Path
import torch
import reconstruction.pipeline as P
import twin
from hemicube.validate import end_to_end

torch.set_num_threads(1)
footprint, res, out = sys.argv[1], int(sys.argv[2]), Path(sys.argv[3])
_orig = P.ReconstructConfig


def forced(*a, **k):
    return _orig(*a, **{**k, "footprint": footprint})


forced.resolution = _orig.resolution
P.ReconstructConfig = forced
rig = twin.load_rig("mini")
result = {}
for name in sys.argv[4:]:
    metrics, rows, _ = end_to_end(rig, name, "cpu", out / name, res, 1, False)
    result[name] = {row["metric"]: row["value"] for row in rows}
    print(name, {k: round(v, 4) if isinstance(v, float) else v for k, v in result[name].items()}, file=sys.stderr, flush=True)
print(json.dumps({"footprint": footprint, "resolution": res, "samples": result}, indent=1, default=str))

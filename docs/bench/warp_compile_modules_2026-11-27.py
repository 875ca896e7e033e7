"""The cold-cache compile time of each forward-only Warp module, with and without adjoint code (issue #12: compilation
counts in the end-to-end run). Each setting compiles in a fresh process with an empty kernel cache.

    python docs/bench/warp_compile_modules_2026-11-27.py OUT.json DEVICE      (DEVICE: cpu or cuda)

Only modules whose kernels have concrete types compile on load; generic ones (basis_jvp, the exact lumitexel
kernels) compile per overload at their first launch, so their load here measures almost nothing (their times in a
real run: docs/bench/warp_compile_timed.py). A record of how the figures were measured, not part of the pipeline.
"""
import json
import os
import subprocess
import sys
import tempfile

MODULES = ("twin.camera.imaging", "twin.camera.sensor", "twin.camera.hdr")
CHILD = """
import json, sys, time, warp as wp
wp.config.quiet = True
wp.init()
import importlib
for name in sys.argv[2:]:
    importlib.import_module(name)
out = {}
for name in sys.argv[2:]:
    m = wp.get_module(name)
    m.options["enable_backward"] = sys.argv[1] == "1"
    t = time.perf_counter()
    wp.load_module(m, device=DEVICE)
    out[name] = time.perf_counter() - t
print(json.dumps(out))
"""

out_path, device = sys.argv[1], sys.argv[2]
rec = {"device": device, "modules": {}}
for backward in ("1", "0"):
    env = {**os.environ, "WARP_CACHE_PATH": tempfile.mkdtemp()}
    run = subprocess.run([sys.executable, "-c", CHILD.replace("DEVICE", repr(device)), backward, *MODULES],
                         env=env, capture_output=True, text=True, check=True)
    for name, s in json.loads(run.stdout.strip().splitlines()[-1]).items():
        rec["modules"].setdefault(name, {})["with_adjoints_s" if backward == "1" else "forward_only_s"] = s
print(json.dumps(rec, indent=1))
with open(out_path, "w") as f:
    json.dump(rec, f, indent=1)

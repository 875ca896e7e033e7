"""Run `hemicube ARGS` and record how long Warp's kernel compilation took in it (issue #12: the end-to-end run counts
compilation, and says how long it takes).

    python docs/bench/warp_compile_timed.py OUT.json -- capture --rig paper --device cuda ...

Wraps warp's Module._compile (code generation and the compiler, for each module the kernel cache lacks) with a
synchronised timer; writes {"argv", "rc", "compile_s", "modules": [[name, seconds, compiled], ...]} to OUT.json and
exits with the command's status. A record of how the number was measured, not part of the pipeline.
"""
import json
import sys
import time

import warp._src.context as wpc

from hemicube.cli import main

out_path, args = sys.argv[1], sys.argv[sys.argv.index("--") + 1:]
modules = []
compile_module = wpc.Module._compile


def timed(self, *a, **k):
    t = time.perf_counter()
    compiled = compile_module(self, *a, **k)
    modules.append([self.name, round(time.perf_counter() - t, 3), bool(compiled)])
    return compiled


wpc.Module._compile = timed
rc = main(args)
with open(out_path, "w") as f:
    json.dump({"argv": args, "rc": rc, "compile_s": round(sum(m[1] for m in modules if m[2]), 3), "modules": modules},
              f, indent=1)
sys.exit(rc)

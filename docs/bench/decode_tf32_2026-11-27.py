"""The fit's lumitexel decode (reconstruction.finetune._decode_rows) in float32 and in TF32: seconds for n paper-rig
texels (mean of 3 after a warm-up), and the TF32 lumitexels' log1p difference from float32's; float32 is run twice and
checked bitwise equal to itself (exit 1 if not).

    python docs/bench/decode_tf32_2026-11-27.py OUT.json [TEXELS]      (CUDA; on a CPU both are float32)

Printed on an H100 in this session's device call (65,536 texels): float32 0.0578 / 0.0597 s, TF32 0.0292 s, log1p
within 2.6e-3 (RMS 5.7e-5); that output was not kept as a file. A record of how the figures were measured.
"""
import json
import sys
import time

import torch

from bench_setup import finetune_texels
from reconstruction.finetune import _decode_rows, grey_to_rgb
from twin.optics.torch_ops import tf32_products

out_path, n = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 65536
dev = "cuda" if torch.cuda.is_available() else "cpu"
rig, model, lines, W, z, hold = finetune_texels("paper", n, dev)
x = torch.as_tensor(grey_to_rgb(z)).to(dev)
sync = torch.cuda.synchronize if dev == "cuda" else (lambda: None)
res, out = {"device": torch.cuda.get_device_name(0) if dev == "cuda" else "cpu", "texels": n}, {}
for name, on in (("float32", False), ("tf32", True), ("float32_again", False)):
    with tf32_products(on):
        _decode_rows(model, x, 16384, x.device)
        sync()
        t = time.perf_counter()
        for _ in range(3):
            m = _decode_rows(model, x, 16384, x.device)
        sync()
        res[f"{name}_s"] = (time.perf_counter() - t) / 3
        out[name] = torch.log1p(m)
d = (out["float32"] - out["tf32"]).abs()
res.update(max_abs_log1p=float(d.max()), rms_log1p=float(d.square().mean().sqrt()),
           float32_same_bits=bool(torch.equal(out["float32"], out["float32_again"])))
print(json.dumps(res, indent=1))
with open(out_path, "w") as f:
    json.dump(res, f, indent=1)
sys.exit(0 if res["float32_same_bits"] else 1)

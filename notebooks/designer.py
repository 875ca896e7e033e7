# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Comparing capture designs
#
# A pattern designer's question: *how many lighting patterns, and which ones?* Here three designs for the
# mini rig are scored side by side with `hemicube design evaluate` (the same as the command line):
#
# - **learned-8**: 8 signed patterns learned together with the network;
# - **learned-3**: 3 learned patterns (fewer photos, a faster capture);
# - **hadamard-8**: 8 fixed Hadamard patterns; only the decoder learns.
#
# Each is trained for the same small budget with three seeds (CI runs this notebook, so the budget is
# tiny: the numbers show the method, `docs/designer.md` has a real comparison), and scored on the same
# test texels. The noise, time and duty figures come from the sensor and LED-controller models.

# %%
import os

os.environ.setdefault("MPLBACKEND", "Agg")

import json
import tempfile
from pathlib import Path

from IPython.display import Image, display

from hemicube.design import evaluate

work = Path(tempfile.mkdtemp(prefix="designer-"))
designs = {"learned-8": ("learned", 8), "learned-3": ("learned", 3), "hadamard-8": ("hadamard", 8)}
for name, (family, count) in designs.items():
    (work / f"{name}.toml").write_text(f"""format = "hemicube-design"
version = 1
name = "{name}"
rig = "mini"

[patterns]
family = "{family}"
count = {count}

[training]
steps = 60
batch = 32
seeds = [0, 1, 2]
""")
paths = [str(work / f"{n}.toml") for n in designs]

# %% [markdown]
# ## The table
#
# `heldout_eq3` is the test loss (paper Eq. 3) averaged over the seeds, `heldout_eq3_std` its spread;
# `snr_median` the measurement SNR at the plan's exposures; `capture_s` the pattern photos plus their
# upload; `duty_peak` / `duty_mean_max` the LED drive.

# %%
evaluate(paths, work / "out", progress=False)
result = json.loads((work / "out" / "designs.json").read_text())
rows = {r["design"]: r for r in result["designs"]}

# %% [markdown]
# ## The plots: test loss with each seed, and the SNR of every measurement

# %%
display(Image(filename=str(work / "out" / "heldout.png")))
display(Image(filename=str(work / "out" / "snr.png")))

# %% [markdown]
# ## The patterns, as crosses of the cube's unfolded boards (+ frames and − frames)

# %%
for name in designs:
    print(name)
    display(Image(filename=str(work / "out" / name / "patterns.png")))

# %% [markdown]
# ## Reading the conclusion off the numbers
#
# A network only scores a design when it uses its measurements: its test loss must lie well below
# `blind_eq3`, the loss of the best predictor that ignores them. And a difference between two designs
# means something only when it is larger than the seeds' spread.

# %%
for r in rows.values():
    ratio = r["heldout_eq3"] / r["blind_eq3"]
    print(f"{r['design']}: test loss {r['heldout_eq3']:.3f} = {ratio:.2f} x the blind predictor's "
          f"({'uses its measurements' if ratio < 0.5 else 'too close to blind: train longer before comparing'})")
best = min(rows.values(), key=lambda r: r["heldout_eq3"])
for r in rows.values():
    if r is best:
        continue
    gap = r["heldout_eq3"] - best["heldout_eq3"]
    spread = max(best["heldout_eq3_std"], r["heldout_eq3_std"])
    verdict = "a real difference" if gap > 2 * spread else "within the seeds' spread: not distinguishable"
    print(f"{best['design']} vs {r['design']}: test loss {best['heldout_eq3']:.3f} vs {r['heldout_eq3']:.3f} "
          f"(gap {gap:.3f}, spread {spread:.3f}): {verdict}; capture {best['capture_s']:.1f} s vs "
          f"{r['capture_s']:.1f} s")
print("how each figure was computed:")
for k, v in result["how"].items():
    print(f"  {k}: {v}")

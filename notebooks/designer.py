# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.7
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
evaluate(paths, work / "out", progress=False, study=work / "study.json")
result = json.loads((work / "out" / "designs.json").read_text())

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
# `hemicube design evaluate` writes a verdict on every pair of designs into `designs.json`
# (`twin/design/verdict.py`). A difference is **real** only when each design has at least three seeds, Welch's
# t-test on their test losses gives p < 0.05, every network scores at least 2x below `blind_eq3` (the best
# predictor that ignores the measurements: a network near it has not learned to use its photos) and every held-out
# curve moved less than 1 % over the last 20 % of its steps. Otherwise it is **not resolved**, with every reason.
# With this notebook's tiny budget expect "not resolved": `docs/designer.md` has comparisons trained long enough.
#
#
# `--study FILE.json` (here `study=`) records a comparison as a study: the same numbers with the command, the
# commit, the versions, the device and the time. What follows is generated from that record, the verdicts computed
# again from its per-seed losses and curves (`twin/design/study.py`).

# %%
from twin.design.study import load_study, study_lines

print("\n".join(study_lines(load_study(work / "study.json"))))
print("how each figure was computed:")
for k, v in result["how"].items():
    print(f"  {k}: {v}")

# %% [markdown]
# ## The studies recorded in `docs/designs/`
#
# Each `docs/designs/*.json` is one study's record, written by `hemicube design evaluate ... --study` with budgets
# long enough to mean something; their verdicts, computed the same way:

# %%
import hemicube

recorded = sorted((Path(hemicube.__file__).resolve().parents[1] / "docs" / "designs").glob("*.json"))
for path in recorded:
    print("\n".join(study_lines(load_study(path))), end="\n\n")
print(f"{len(recorded)} recorded stud{'y' if len(recorded) == 1 else 'ies'} in docs/designs/")

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
# # A tour of the rig
#
# The twin's model of the OpenSVBRDF light stage: a 70 x 70 x 40 cm cube with 16,384 LEDs on 7 boards
# (four walls, two top boards, and a bottom board under a translucent acrylic plate) and two cameras
# looking down at the sample. Units are millimetres; world +z points up out of the sample, whose plane
# is z = -122 mm.
#
# This notebook runs headless (CI executes it): pyvista renders off-screen through EGL and the
# pictures are shown as PNGs.

# %%
import os

# Off-screen VTK without an X server (must be set before pyvista is imported), and a non-GUI
# matplotlib backend; the inline backend below draws the figures into the notebook.
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
os.environ.setdefault("MPLBACKEND", "Agg")

import tempfile
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Image, display
from matplotlib.colors import to_rgb

# pyvista imports tqdm.auto, which warns in a kernel without ipywidgets: harmless, and only noise here
warnings.filterwarnings("ignore", message="IProgress not found")

import twin
from twin.view.cross_plot import cross_rgb
from twin.capture.patterns import PatternSet
from twin.view.rig_view import BOARD_COLOURS, show_rig

# %matplotlib inline

# %% [markdown]
# ## The paper rig
# `twin.load_rig("paper")` builds the full device from the released layout. Its summary lists the
# boards and the cameras (the secondary camera's calibration is assumed: none was released).

# %%
rig = twin.load_rig("paper")
info = rig.summary()
print(f"rig {info['name']}: {info['num_leds']} LEDs ({info['num_upper_leds']} upper, "
      f"{info['num_bottom_leds']} bottom)")
for b in info["boards"]:
    print(f"  {b['name']:<8} face {b['face']:<6} grid {b['grid'][0]}x{b['grid'][1]}: {b['leds']} LEDs")
for name, cam in info["cameras"].items():
    print(f"  camera {name:<9} centre {np.round(cam['centre'], 1).tolist()} mm, "
          f"{cam['resolution'][0]}x{cam['resolution'][1]} px, fx {cam['fx']:.0f}"
          + ("  (ASSUMED)" if cam["assumed"] else ""))

# %% [markdown]
# ## The rig in 3-D
# `show_rig` draws the boards, the LEDs (here coloured by board), both camera frusta down to the
# sample plane, the sample with its holder frame and ArUco markers, and the acrylic plate. The -y wall
# and the top are cut away (outline and small dots) so that the inside of the cube is visible.

# %%
tmp = Path(tempfile.mkdtemp(prefix="tour_of_the_rig_"))
png = show_rig(rig, output=tmp / "rig.png", window_size=(1000, 750))
display(Image(filename=str(png)))

# %% [markdown]
# ## A pattern on the unfolded cube
# A lighting pattern gives every LED an 8-bit RGB drive level. Here: the elevation of each LED seen
# from the sample centre, normalised to [0, 1] (LEDs below the sample plane, i.e. the bottom board,
# are off). The "cross" image unfolds the cube: the top in the middle, the walls folded out around
# it, and the bottom board on the right.

# %%
d = rig.led_positions - np.asarray(rig.sample.origin)
elevation = np.arcsin(np.clip(d[:, 2] / np.linalg.norm(d, axis=1), -1, 1))
weights = np.clip(elevation, 0, None) / elevation.max()
pattern = PatternSet.from_weights(weights[None], names=("elevation",), rig="paper",
                                  note="elevation of each LED seen from the sample centre")
print(f"{pattern.num_patterns} frame, {pattern.num_leds} LEDs, levels "
      f"{pattern.levels.min()}..{pattern.levels.max()}")

fig, ax = plt.subplots(figsize=(7.5, 5))
ax.imshow(cross_rgb(rig, pattern.weights[0]), interpolation="nearest")
ax.set_title(f"pattern '{pattern.names[0]}' on the unfolded cube")
ax.set_axis_off()
plt.show()

# %% [markdown]
# ## The mini rig's cross layout
# The mini rig (CI and demos) keeps the paper rig's geometry with every 6th upper LED and every 8th
# bottom LED. In the cross image each of its LEDs fills the block of board pixels nearest to it, so
# every board keeps its full footprint. Colours match the 3-D view's board colours.

# %%
mini = twin.load_rig("mini")
palette = np.array([to_rgb(BOARD_COLOURS[b % len(BOARD_COLOURS)]) for b in range(len(mini.boards))])
img = cross_rgb(mini, palette[mini.leds.board])

fig, ax = plt.subplots(figsize=(7.5, 5))
ax.imshow(img, interpolation="nearest")
for b, board in enumerate(mini.boards):
    col, row = mini.leds.cross_pixel[mini.leds.board == b].mean(0)
    ax.text(col, row, f"{board.name}\n{(mini.leds.board == b).sum()} LEDs", ha="center", va="center",
            fontsize=8, color="white", weight="bold")
cp = mini.leds.cross_pixel
ax.plot(cp[:, 0], cp[:, 1], "k.", markersize=2)  # the LEDs themselves
ax.set_title(f"mini rig: {mini.num_leds} LEDs on the unfolded cube")
ax.set_axis_off()
plt.show()

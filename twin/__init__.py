"""hemicube twin: a digital twin of the OpenSVBRDF light-hemicube.

Public API (names kept stable for the other packages, external code and tests):
    twin.load_rig(name_or_dir) -> Rig
    twin.lumitexels(rig, position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, ...)
    twin.measurements(rig, ..., patterns)
Heavy modules (warp, torch, pyvista) are imported lazily.

Sub-packages, one per physical thing (docs/architecture.md has the picture):
    twin.rig        the rig model (LEDs, boards, cameras' calibration, sample plane, holder frame), its folder
                    format, the built-in rigs, the OpenSVBRDF importer, the cross layout, units and frames
    twin.optics     GGX, the LED emission profile, the Warp kernels of Eq. 1-2, the public forward API, torch
    twin.materials  SVBRDF texture maps (the OpenSVBRDF contract), built-in samples, EXR files
    twin.camera     image formation (pixel rays, hits, radiance), the sensor, Bayer/PFNC formats, HDR merge
    twin.capture    pattern files and sets, the capture plan, the session folder, device backends
    twin.targets    calibration targets the twin photographs (ChArUco board, flat-field source, diffuse plate,
                    ColorChecker)
    twin.design     figures of merit of capture designs (noise, multiplexing gain, device costs, design files)
    twin.view       the pyvista view of the rig, cross-image plots, the rig as glTF
Beside them: the twin's commands (cli.py), its self-checks (checks.py), benchmarks (bench.py), batches on Ray
(batch.py), atomic file writes (atomic.py), the folders' locks (lock.py), contained paths (paths.py) and the
packages' exports loaded on first use (lazy.py).
"""
from __future__ import annotations

from twin.lazy import lazy_exports as _lazy_exports
from twin.rig.model import Rig, RigError  # noqa: F401

__all__ = ["Rig", "RigError", "load_rig", "save_rig", "lumitexels", "measurements"]


def load_rig(name_or_dir) -> Rig:
    """The Rig of a built-in rig by name ("paper", "mini"; one shared instance each) or of a rig folder (a path,
    twin.rig.format: lengths in mm, or converted to mm from the folder's declared `length_unit`). The rig's arrays
    are in the world frame of twin.rig.units: LED positions (L, 3) mm, unit normals (L, 3), cameras' K (3, 3) in
    pixels. A RigError says why a folder cannot be read."""
    from pathlib import Path

    from twin.rig.builtin import BUILTIN

    if isinstance(name_or_dir, str) and name_or_dir in BUILTIN:
        return _builtin(name_or_dir)
    path = Path(name_or_dir)
    if not path.exists():
        raise RigError(f"{name_or_dir!r} is neither a built-in rig ({', '.join(BUILTIN)}) nor an existing folder")
    from twin.rig.format import load_rig_dir

    return load_rig_dir(path)


_CACHE: dict = {}


def _builtin(name: str) -> Rig:
    from twin.rig.builtin import BUILTIN

    if name not in _CACHE:  # rigs are immutable, so one instance can be shared
        _CACHE[name] = BUILTIN[name]()
    return _CACHE[name]


# the public functions that live in heavier modules, loaded on first use (the forward model imports Warp): the
# functions themselves, with their signatures and docstrings (units, shapes), not wrappers
_LAZY = {"lumitexels": "twin.optics.forward", "measurements": "twin.optics.forward", "save_rig": "twin.rig.format"}
__getattr__, __dir__ = _lazy_exports(__name__, _LAZY)

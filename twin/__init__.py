"""hemicube twin: a digital twin of the OpenSVBRDF light-hemicube.

Public API (names kept stable for later issues and external tests):
    twin.load_rig(name_or_dir) -> Rig
    twin.lumitexels(rig, position, normal, tangent, rho_d, rho_s, alpha_x, alpha_y, ...)
    twin.measurements(rig, ..., patterns)
Heavy modules (warp, torch, pyvista) are imported lazily.
"""
from __future__ import annotations

from .rig import Rig, RigError  # noqa: F401

__all__ = ["Rig", "RigError", "load_rig", "save_rig", "lumitexels", "measurements"]


def load_rig(name_or_dir) -> Rig:
    """A built-in rig by name ("paper", "mini") or a rig folder (twin.rig_format)."""
    from pathlib import Path

    from .builtin_rigs import BUILTIN

    if isinstance(name_or_dir, str) and name_or_dir in BUILTIN:
        return _builtin(name_or_dir)
    path = Path(name_or_dir)
    if not path.exists():
        raise RigError(f"{name_or_dir!r} is neither a built-in rig ({', '.join(BUILTIN)}) nor an existing folder")
    from .rig_format import load_rig_dir

    return load_rig_dir(path)


_CACHE: dict = {}


def _builtin(name: str) -> Rig:
    from .builtin_rigs import BUILTIN

    if name not in _CACHE:  # rigs are immutable, so one instance can be shared
        _CACHE[name] = BUILTIN[name]()
    return _CACHE[name]


def save_rig(rig: Rig, directory, overwrite: bool = False):
    from .rig_format import save_rig as _save

    return _save(rig, directory, overwrite=overwrite)


def lumitexels(*args, **kwargs):
    from .forward import lumitexels as _f

    return _f(*args, **kwargs)


def measurements(*args, **kwargs):
    from .forward import measurements as _f

    return _f(*args, **kwargs)

"""Names a package exports from heavier modules, loaded on first use (PEP 562), so that importing the package imports
neither Warp nor torch. Each name is the object itself, with its own signature and docstring, not a wrapper:

    __getattr__, __dir__ = lazy_exports(__name__, {"lumitexels": "twin.optics.forward"})

Used by the four packages' `__init__` (twin, calibration, reconstruction, hemicube); imports nothing itself."""
from __future__ import annotations


def lazy_exports(package: str, lazy: dict[str, str]):
    """(`__getattr__`, `__dir__`) for the package named `package`: `lazy` maps each exported name to the module
    that defines it under that name. A name's first lookup imports its module and stores the object in the package,
    so later lookups are plain ones; `dir(package)` lists the lazy names beside the loaded ones."""
    import importlib
    import sys

    def __getattr__(name: str):
        if name in lazy:
            value = getattr(importlib.import_module(lazy[name]), name)
            setattr(sys.modules[package], name, value)
            return value
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(lazy))

    return __getattr__, __dir__

"""The front of hemicube twin: the `hemicube` command (hemicube.cli), whose sub-commands each package
registers (twin.cli, calibration.cli, reconstruction.cli; the designer's is hemicube.design), and the main job
that spans them, `hemicube validate` (hemicube.validate). Nothing below imports this package.

Exported here (`__all__`, each loaded on first use: `import hemicube` imports neither Warp nor torch):
    main             the `hemicube` command, from Python: main(["validate", "--rig", "mini"]) -> exit code
    run_validation   `hemicube validate`: checks, then capture -> reconstruct -> score one sample
    run_suite        `hemicube validate --suite`: the same on every sample of a suite"""
from __future__ import annotations

from twin.lazy import lazy_exports as _lazy_exports

# each exported name and the module that defines it, loaded on first use
_LAZY = {"main": "hemicube.cli", "run_validation": "hemicube.validate", "run_suite": "hemicube.validate"}
__all__ = list(_LAZY)
__getattr__, __dir__ = _lazy_exports(__name__, _LAZY)

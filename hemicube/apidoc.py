"""The API reference, generated from the docstrings by pdoc (`make api`, or `python -m hemicube.apidoc -o DIR`):
one HTML page per module of twin, calibration, reconstruction and hemicube, built by the tests, never committed."""
from __future__ import annotations

import argparse
import importlib
from pathlib import Path

PACKAGES = ("twin", "calibration", "reconstruction", "hemicube")


def build(output) -> Path:
    """Write the reference to `output` (a folder); returns its index.html. The names a package loads on first use
    (every package's exports from heavy modules: PEP 562, twin.lazy) are loaded first, since pdoc reads a module's
    own attributes."""
    try:
        import pdoc
    except ImportError:
        raise ValueError("the API reference needs pdoc: pip install 'hemicube-twin[docs]'") from None
    for name in PACKAGES:
        module = importlib.import_module(name)
        for public in getattr(module, "__all__", ()):
            getattr(module, public)
    out = Path(output)
    pdoc.pdoc(*PACKAGES, output_directory=out)
    return out / "index.html"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m hemicube.apidoc", description=__doc__)
    p.add_argument("-o", "--output", default="api", help="folder for the HTML pages (default: %(default)s)")
    print(f"API reference: {build(p.parse_args(argv).output)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

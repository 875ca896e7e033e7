"""The public API: every name a package exports (`__all__`) is the object itself, with its real signature and a
docstring, also where it is loaded on first use (twin's forward model imports Warp only when used)."""
from __future__ import annotations

import importlib
import inspect

import pytest

WRAPPER = [inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD]


@pytest.mark.parametrize("package", ["twin"])
def test_exported_names_have_a_signature_and_a_docstring(package):
    module = importlib.import_module(package)
    for name in module.__all__:
        obj = getattr(module, name)
        assert len((obj.__doc__ or "").strip()) > 40, f"{package}.{name} has no docstring"
        if callable(obj) and not isinstance(obj, type):
            kinds = [p.kind for p in inspect.signature(obj).parameters.values()]
            assert kinds != WRAPPER, f"{package}.{name} shows (*args, **kwargs), not its signature"
        assert name in dir(module)


def test_the_forward_model_names_its_units_and_shapes():
    import twin

    assert "position" in inspect.signature(twin.lumitexels).parameters
    assert "patterns" in inspect.signature(twin.measurements).parameters
    for f in (twin.lumitexels, twin.measurements):
        assert "(P, " in f.__doc__ or "P points" in f.__doc__, f.__name__


def test_the_api_reference_builds_with_every_exported_function(tmp_path):
    """`make api` (hemicube.apidoc, pdoc): a page per package, twin's exported functions on its page with their
    signatures (pdoc cannot read a name a package loads on first use unless it is loaded: apidoc does)."""
    pytest.importorskip("pdoc")
    from hemicube.apidoc import PACKAGES, build

    index = build(tmp_path / "api")
    assert index.is_file()
    for package in PACKAGES:
        assert (tmp_path / "api" / f"{package}.html").is_file(), package
    page = (tmp_path / "api" / "twin.html").read_text()
    for name in ("lumitexels", "measurements", "save_rig", "load_rig"):
        assert f'id="{name}"' in page, name
    assert "position" in page and "alpha_x" in page

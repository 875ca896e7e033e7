"""The public API: every name a package exports (`__all__`) is the object itself, with its real signature and a
docstring that states its units and shapes, also where it is loaded on first use (twin.lazy: importing a package
imports neither Warp nor torch)."""
from __future__ import annotations

import importlib
import inspect
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ["twin", "calibration", "reconstruction", "hemicube"]
WRAPPER = [inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD]

# What each exported name's docstring must say of its units and shapes (substrings, as written there): a new export
# needs its entry. An empty list: a name with no quantities of its own (an error class).
UNITS = {
    "twin.Rig": ["mm", "(L, 3)", "(3, 3)", "pixels"],
    "twin.RigError": [],
    "twin.load_rig": ["mm", "(L, 3)", "pixels"],
    "twin.save_rig": ["mm"],
    "twin.lumitexels": ["(P, 3) mm", "(P,)", "(P, L, 3)", "W m^-2 sr^-1"],
    "twin.measurements": ["(P, K, 3)", "(K, L, 3)", "mm", "drive"],
    "calibration.calibrate_cameras": ["(3, 3)", "pixels", "mm", "degrees", "%"],
    "calibration.calibrate_vignetting": ["(H, W)", "pixels", "%", "degrees"],
    "calibration.calibrate_colour": ["(3, 3)", "ΔE2000", "%", "pixels"],
    "calibration.calibrate_leds_from_plate": ["(3,)", "mm", "degrees", "%", "pixels"],
    "calibration.stage": ["frames", "pixels"],
    "calibration.calibrate": ["mm", "pixels", "degrees", "%"],
    "reconstruction.reconstruct": ["(R, R, 3)", "(R * R, 72)", "mm", "[0, 1]", "seconds"],
    "reconstruction.ReconstructConfig": ["texels", "mm"],
    "reconstruction.evaluate": ["pixels", "degrees", "dB", "seconds"],
    "reconstruction.map_errors": ["(H, W)", "texels", "degrees", "%"],
    "reconstruction.validation_set": ["(20, 3)", "(28, 3)", "degrees", "mm", "pixels"],
    "reconstruction.novel_view_scores": ["(H, W)", "(H, W, 3)", "dB", "degrees", "[0, 1]"],
    "reconstruction.load_pretrained": ["(B, views, L)", "(B, L)"],
    "hemicube.main": ["list of strings", "exit code"],
    "hemicube.run_validation": ["mm", "texels", "pixels", "degrees", "seconds"],
    "hemicube.run_suite": ["texels", "pixels", "degrees", "seconds"],
}


def _exports():
    for package in PACKAGES:
        module = importlib.import_module(package)
        for name in module.__all__:
            yield package, module, name


@pytest.mark.parametrize("package", PACKAGES)
def test_exported_names_have_a_signature_and_a_docstring(package):
    module = importlib.import_module(package)
    assert 3 <= len(module.__all__) <= 8 and len(set(module.__all__)) == len(module.__all__), module.__all__
    assert len((module.__doc__ or "").strip()) > 40, f"{package} has no module docstring"
    for name in module.__all__:
        assert name in dir(module)
        obj = getattr(module, name)
        doc = inspect.getdoc(obj) or ""
        assert len(doc) > 40, f"{package}.{name} has no docstring"
        assert not doc.startswith(f"{name}("), f"{package}.{name}: the dataclass's generated docstring, not its own"
        assert max(len(line) for line in (obj.__doc__ or "").splitlines()) <= 120, f"{package}.{name}: a long line"
        if callable(obj) and not (isinstance(obj, type) and issubclass(obj, BaseException)):
            kinds = [p.kind for p in inspect.signature(obj).parameters.values()]
            assert kinds != WRAPPER, f"{package}.{name} shows (*args, **kwargs), not its signature"
        assert obj.__module__ == package or obj.__module__.startswith(package + "."), f"{package}.{name}"


def test_every_exported_name_states_its_units_and_shapes():
    exported = {f"{package}.{name}" for package, _, name in _exports()}
    assert exported == set(UNITS), "UNITS lists each exported name: " + str(exported ^ set(UNITS))
    missing = {}
    for package, module, name in _exports():
        doc = inspect.getdoc(getattr(module, name))
        absent = [word for word in UNITS[f"{package}.{name}"] if word not in doc]
        if absent:
            missing[f"{package}.{name}"] = absent
    assert missing == {}


def test_the_forward_model_names_its_units_and_shapes():
    import twin

    assert "position" in inspect.signature(twin.lumitexels).parameters
    assert "patterns" in inspect.signature(twin.measurements).parameters
    for f in (twin.lumitexels, twin.measurements):
        assert "(P, " in f.__doc__ or "P points" in f.__doc__, f.__name__


def test_importing_the_packages_imports_neither_torch_nor_warp():
    """`import twin, calibration, reconstruction, hemicube` in a fresh process, and listing what they export: neither
    torch nor Warp is imported (each exported name from a heavy module is loaded on its first use), and a lazy name,
    once used, is the defining module's own object."""
    code = ("import sys\nimport twin, calibration, reconstruction, hemicube\n"
            "names = [n for p in (twin, calibration, reconstruction, hemicube) for n in p.__all__ if n in dir(p)]\n"
            "print(len(names), sorted(m for m in ('torch', 'warp') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split()[-1] == "[]", r.stdout
    assert int(r.stdout.split()[0]) == len(UNITS)

    import calibration
    import calibration.leds

    assert calibration.calibrate_leds_from_plate is calibration.leds.calibrate_leds_from_plate
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        calibration.nothing  # noqa: B018


def test_the_api_reference_builds_with_every_exported_function(tmp_path):
    """`make api` (hemicube.apidoc, pdoc): a page per package, each package's exported names on its page with their
    signatures (pdoc cannot read a name a package loads on first use unless it is loaded: apidoc does)."""
    pytest.importorskip("pdoc")
    from hemicube.apidoc import PACKAGES as DOCUMENTED, build

    assert set(DOCUMENTED) == set(PACKAGES)
    index = build(tmp_path / "api")
    assert index.is_file()
    for package in PACKAGES:
        page = (tmp_path / "api" / f"{package}.html").read_text()
        for name in importlib.import_module(package).__all__:
            assert f'id="{name}"' in page, f"{package}.{name}"
    page = (tmp_path / "api" / "twin.html").read_text()
    assert "position" in page and "alpha_x" in page

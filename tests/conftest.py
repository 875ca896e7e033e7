"""Shared fixtures: the released OpenSVBRDF reference folder, the (cached) rigs and the `device` each kernel test
runs on; the end-to-end files (LONG_FILES: first in `make test`, left out of `make test-fast`).

The reference folder lives beside the repository root (`../shared/reference/opensvbrdf_lightstage`).
It is present on CI and on developers' machines but not on a user's clone, so every test that needs it
goes through the `reference_dir` fixture, which skips with a fixed reason when it is absent.
"""
from __future__ import annotations

import functools
import os
from pathlib import Path

# One BLAS / OpenMP thread a test process, set before numpy and torch load their thread pools (they read it then),
# and inherited by the processes the tests start (the CLI, the suite's workers, torchrun's). The tests run one
# process per core (pytest-xdist) beside processes of their own, so the cores are always shared, and an OpenMP
# thread that waits for a descheduled sibling spins on a core another process needs (measured in docs/performance.md,
# "CI"). A value already set is kept.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402 - after the thread count
import pytest  # noqa: E402

os.environ.setdefault("WARP_CACHE_PATH", str(Path(__file__).resolve().parents[1] / ".cache" / "warp"))

REFERENCE_DIR = Path(__file__).resolve().parents[2] / "shared" / "reference" / "opensvbrdf_lightstage"
REFERENCE_SKIP_REASON = ("reference data ../shared/reference not present "
                         "(it is on CI and dev machines, not on a user's clone)")
NUM_UPPER = 12 * 1024  # 6 boards x 64 x 32, as released


def reference_present() -> bool:
    return (REFERENCE_DIR / "lights.bin").is_file()


# The long files, longest first: the material suite, then those of a minute or more on one core
# (docs/performance.md, "CI"). `make test` runs them first: pytest-xdist hands whole files to its processes in
# collection order (the Makefile turns off xdist's own reordering by test count, which queued these last), so the
# short files fill both cores at the end instead of one long file running on alone.
LONG_FILES = ("test_validate_suite.py", "test_scaleout.py", "test_hardware_capture.py", "test_bench_pipeline.py",
              "test_capture.py", "test_alignment.py", "test_readme_tour.py", "test_validate.py", "test_train.py",
              "test_design.py", "test_reconstruct_resume.py")

# The end-to-end files, marked `e2e`, which `make test-fast` leaves out: the long files above, and the calibration
# procedures run on rendered photos, two-process training and the notebooks (each a minute or more on one core).
END_TO_END_FILES = LONG_FILES + ("test_calibration.py", "test_calibration_colour.py", "test_calibration_leds.py",
                                 "test_distributed.py", "test_notebooks.py")


def pytest_collection_modifyitems(items):
    """The long files first, longest first (LONG_FILES), the rest in their own order; the tests of
    END_TO_END_FILES marked `e2e` (`make test-fast` runs `-m "not e2e and not slow"`)."""
    e2e = set(END_TO_END_FILES)
    for item in items:
        if item.path.name in e2e:
            item.add_marker(pytest.mark.e2e)
    rank = {name: k for k, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FILES)))


@functools.cache
def devices() -> tuple[str, ...]:
    """The devices the `device` fixture runs on: the CPU, and the first CUDA device where both Warp and torch see
    one ("cuda:0" names the same device to both; the kernels' tests hand it to Warp, the fit's to torch, some to
    both). Asked once, when the first test that takes `device` is collected: it loads Warp and torch."""
    import torch
    import warp as wp

    return ("cpu", "cuda:0") if wp.get_cuda_device_count() > 0 and torch.cuda.is_available() else ("cpu",)


@pytest.hookimpl(trylast=True)  # after the tests' own parametrize marks: the device ends the id, test_x[mse-cpu]
def pytest_generate_tests(metafunc):
    """A test that takes `device` runs once per entry of devices(), its id ending in cpu or cuda:0."""
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", devices(), indirect=True)


@pytest.fixture
def device(request) -> str:
    """A device name valid for both Warp and torch: "cpu", and "cuda:0" where present (devices())."""
    return request.param


@pytest.fixture(scope="session")
def reference_dir() -> Path:
    if not reference_present():
        pytest.skip(REFERENCE_SKIP_REASON)
    return REFERENCE_DIR


@pytest.fixture(scope="session")
def released_lights(reference_dir) -> tuple[np.ndarray, np.ndarray]:
    """lights.bin read directly: float32 (2, N, 3) -> (positions, stored OUTWARD normals)."""
    raw = np.fromfile(reference_dir / "lights.bin", dtype="<f4")
    assert raw.size == 2 * NUM_UPPER * 3
    lights = raw.reshape(2, -1, 3)
    return lights[0], lights[1]


@pytest.fixture(scope="session")
def released_preview(reference_dir) -> np.ndarray:
    """visualize_config_torch.bin read directly: int32 header (128, 192), then N (col, row) pairs."""
    raw = np.fromfile(reference_dir / "visualize_config_torch.bin", dtype="<i4")
    assert tuple(raw[:2]) == (128, 192)
    return raw[2:].reshape(-1, 2)


@pytest.fixture(scope="session")
def released_cam_pos(reference_dir) -> np.ndarray:
    return np.fromfile(reference_dir / "cam_pos.bin", dtype="<f4").astype(np.float64)


@pytest.fixture(scope="session")
def paper():
    import twin

    return twin.load_rig("paper")


@pytest.fixture(scope="session")
def mini():
    import twin

    return twin.load_rig("mini")


@pytest.fixture(scope="module")
def one_torch_thread():
    """Small torch problems: torch's OpenMP threads only add synchronisation, which on a shared 2-core
    machine (CI) costs up to 10x. Restored afterwards. Use with pytestmark = usefixtures("one_torch_thread")."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def validate_dir(tmp_path_factory):
    """A `hemicube validate` output folder whose capture (mini rig, ramps, seed 1: the main job's defaults)
    is taken once per session; reconstruction tests read it, the main-job test resumes it (verified, not
    retaken)."""
    import twin
    from filelock import FileLock

    from twin.capture.runner import capture

    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        out = tmp_path_factory.mktemp("validate")
        capture(twin.load_rig("mini"), "ramps", out / "capture", seed=1, progress=False)
        return out
    # under pytest-xdist every test process has a session of its own: the first takes the capture into the
    # run's shared folder, the others wait for it and take nothing (a finished capture is reused as it is)
    shared = tmp_path_factory.getbasetemp().parent
    with FileLock(str(shared / "validate.lock")):
        capture(twin.load_rig("mini"), "ramps", shared / "validate" / "capture", seed=1, progress=False)
    return shared / "validate"


@pytest.fixture(scope="session")
def imported(reference_dir):
    from twin.rig.opensvbrdf_import import import_opensvbrdf

    return import_opensvbrdf(reference_dir)


class PickleBomb:
    """Unpickling this creates `marker` (via open(marker, "w")): proof that something was unpickled."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def pickle_bomb_array(marker) -> np.ndarray:
    """A 0-d object array that runs PickleBomb on unpickling."""
    a = np.empty((), dtype=object)
    a[()] = PickleBomb(marker)
    return a


def assert_rigs_identical(a, b) -> None:
    """Every array bit-equal with the same dtype, every camera bit-equal, same scalars and digest."""
    from twin.rig.model import LEDs

    assert a.name == b.name
    assert a.num_leds == b.num_leds
    for k in LEDs.ARRAYS:
        x, y = getattr(a.leds, k), getattr(b.leds, k)
        assert x.dtype == y.dtype, k
        assert x.shape == y.shape, k
        assert x.tobytes() == y.tobytes(), k
    assert a.boards == b.boards
    assert list(a.cameras) == list(b.cameras)
    for n in a.cameras:
        ca, cb = a.cameras[n], b.cameras[n]
        for attr in ("K", "dist", "R", "t"):
            x, y = getattr(ca, attr), getattr(cb, attr)
            assert x.dtype == y.dtype and x.shape == y.shape, (n, attr)
            assert x.tobytes() == y.tobytes(), (n, attr)
        assert (ca.name, ca.width, ca.height, ca.sensor, ca.assumed, ca.note) == \
               (cb.name, cb.width, cb.height, cb.sensor, cb.assumed, cb.note)
    assert a.sample == b.sample
    assert a.bottom == b.bottom
    assert (a.frame is None) == (b.frame is None)
    if a.frame is not None:
        for attr in ("inner_size", "outer_size", "height", "marker_dictionary", "marker_size"):
            assert getattr(a.frame, attr) == getattr(b.frame, attr)
        for attr in ("marker_ids", "marker_corners"):
            x, y = getattr(a.frame, attr), getattr(b.frame, attr)
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), attr
    assert (a.led_profile, a.notes, a.length_unit) == (b.led_profile, b.notes, b.length_unit)
    assert a.digest() == b.digest()


def copy_reference(reference_dir: Path, dst: Path) -> Path:
    """A writable copy of the (read-only) reference folder."""
    import shutil

    shutil.copytree(reference_dir, dst, copy_function=shutil.copyfile)
    dst.chmod(0o755)
    for p in dst.iterdir():
        p.chmod(0o644)
    return dst

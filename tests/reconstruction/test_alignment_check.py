"""The alignment check without ground truth (reconstruction/stages/alignment_check.py): it must flag the two faults
that real captures meet (a secondary view 1 px off, a coarse homography ~12 px off), raise no flag on a right
alignment, and stop the pipeline with one line unless the user accepts. Truth comes from the twin's sidecars and
from synthetic pairs whose mapping is known in closed form (tests.reconstruction.test_alignment)."""
from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

import twin
from reconstruction.stages.alignment import AlignConfig, Alignment, AlignmentError, align_views, alignment_error
from reconstruction.stages.alignment_check import CheckConfig, check_alignment
from tests.reconstruction.test_alignment import GOAL_PX, _surface, _texture, _uniform_pair

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _moved(al: Alignment, dx: float, dy: float) -> Alignment:
    return Alignment(al.map + np.float32([dx, dy]), al.homography, dict(al.info))


@pytest.fixture(scope="module")
def mini_pair():
    rig, photos, truth = _uniform_pair(1)
    al = align_views(photos["primary"], photos["secondary"], rig)
    return rig, photos, truth, al


def test_a_right_alignment_is_not_flagged(mini_pair):
    rig, photos, truth, al = mini_pair
    assert alignment_error(al, truth["primary"], truth["secondary"])["median_px"] <= GOAL_PX
    c = check_alignment(photos["primary"], photos["secondary"], al, rig)
    assert c["verified"] and not c["flagged"], c
    assert c["median_shift_px"] < CheckConfig().flag_px / 2, c


@pytest.mark.parametrize("dx, dy", [(1, 0), (0, 1), (-0.8, 0.8)])
def test_a_secondary_view_a_pixel_off_is_flagged(mini_pair, dx, dy):
    rig, photos, truth, al = mini_pair
    c = check_alignment(photos["primary"], photos["secondary"], _moved(al, dx, dy), rig)
    assert c["verified"] and c["flagged"], c
    assert c["median_shift_px"] > 0.75 * np.hypot(dx, dy), c  # it measures the fault (in primary px)


def test_a_coarse_homography_12_px_off_is_flagged_on_the_paper_rig_cameras():
    """The paper rig's cameras binned 3 x 3 (as in the pyramid test), a textured flat sample: the calibrated plane's
    map is right and passes; the same map 12 px off (the size of the failure on glossy samples at full width) is
    flagged."""
    paper = twin.load_rig("paper")
    cams = {n: paper.camera(n).resized(1 / 3) for n in ("primary", "secondary")}
    rig = SimpleNamespace(name="paper/3", camera=cams.__getitem__, frame=paper.frame, sample=paper.sample)
    photos = [_texture(*(4 * _surface(rig, n, raised_mm=0.0)[1]).transpose(2, 0, 1), seed=4).astype(np.float32)
              for n in ("primary", "secondary")]
    right = align_views(*photos, rig, AlignConfig(coarse="calibrated", dense=False))
    ok = check_alignment(*photos, right, rig)
    assert ok["verified"] and not ok["flagged"] and ok["median_shift_px"] < 0.2, ok
    off = check_alignment(*photos, _moved(right, 12 / np.sqrt(2), 12 / np.sqrt(2)), rig)
    # 12 secondary px are more primary px: the secondary sees the plane at 45 deg, the primary from above
    assert off["verified"] and off["flagged"] and off["median_shift_px"] > 10, off


def test_a_textureless_view_is_not_verified_rather_than_flagged(mini_pair):
    rig, photos, _, al = mini_pair
    flat = [np.full_like(p, 0.5) for p in (photos["primary"], photos["secondary"])]
    c = check_alignment(*flat, al, rig)
    assert not c["verified"] and not c["flagged"] and c["median_shift_px"] is None, c


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="CheckConfig"):
        CheckConfig(flag_px=0)


def test_a_flagged_alignment_stops_the_reconstruction_unless_accepted(validate_dir, tmp_path):
    """Flagged (here by a limit no alignment meets), the reconstruction stops with one line naming the way on;
    re-run with accept_alignment, it resumes from the alignment it kept."""
    from reconstruction.pipeline import ReconstructConfig, reconstruct

    strict = replace(ReconstructConfig(), resolution=16, alignment_check=CheckConfig(flag_px=1e-6))
    with pytest.raises(AlignmentError, match=r"still disagree by \d\.\d\d px .*--accept-alignment") as e:
        reconstruct(validate_dir / "capture", tmp_path / "out", strict, progress=False)
    assert "\n" not in str(e.value)
    r = reconstruct(validate_dir / "capture", tmp_path / "out", replace(strict, accept_alignment=True), progress=False)
    assert r.alignment.info["check"]["flagged"]
    assert (tmp_path / "out" / "maps").is_dir()

"""`hemicube capture-many` and `hemicube reconstruct-many` on a real local Ray (docs/scale-out.md): tiny mini-rig
captures made by capture-many, one broken capture folder, reconstruct-many over all three. The broken one is
reported with its error after its bounded retries and does not stop the batch; finished work is skipped on a
second run; a reconstruction whose files were changed afterwards is redone; scores come with the captures'
ground truth. Every command is the installed CLI in its own process, as a user runs it."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("ray")

SAMPLES = """\
rig = "mini"
seed = 2
sample_resolution = 32
[[sample]]
name = "ramps"
[[sample]]
name = "satin@5"
folder = "satin5"
"""


def _hemicube(cwd: Path, *args, ok=(0,)) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-m", "hemicube.cli", *args], cwd=cwd, capture_output=True, text=True,
                       timeout=900)
    assert r.returncode in ok, r.stdout[-3000:] + r.stderr[-3000:]
    return r


def _outcomes(path: Path) -> dict:
    return {o["name"]: o for o in json.loads(path.read_text())["outcomes"]}


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    d = tmp_path_factory.mktemp("many")
    (d / "samples.toml").write_text(SAMPLES)
    first = _hemicube(d, "capture-many", "samples.toml", "-o", "caps", "--jobs", "2")
    (d / "caps" / "broken").mkdir()
    (d / "caps" / "broken" / "manifest.json").write_text("{ not json")
    recon = _hemicube(d, "reconstruct-many", "caps", "-o", "out", "--resolution", "16", "--retries", "1", "--jobs", "2",
                      ok=(1,))  # 1: a capture failed
    return d, first, recon


def test_capture_many_makes_verified_captures(batch):
    from twin.capture.session import CaptureSession

    d, first, _ = batch
    o = _outcomes(d / "caps" / "batch.json")
    assert {k: v["status"] for k, v in o.items()} == {"ramps_seed2": "done", "satin5": "done"}
    for name in o:
        assert "--- done in" in (d / "caps" / "logs" / f"{name}.log").read_text()
        s = CaptureSession.open(d / "caps" / name)
        assert s.complete() and s.header["seed"] == 2 and s.header["resolution"] == 32 and not s.keeps_raw_frames
    assert "2 done, 0 skipped" in first.stdout
    again = _hemicube(d, "capture-many", "samples.toml", "-o", "caps")
    assert "0 done, 2 skipped" in again.stdout
    # the same folder named for another capture (resolution 16): not skipped, and capture() refuses it
    (d / "other.toml").write_text(SAMPLES.replace('name = "satin@5"', 'name = "satin@5"\nsample_resolution = 16'))
    other = _hemicube(d, "capture-many", "other.toml", "-o", "caps", "--retries", "0", ok=(1,))
    o = _outcomes(d / "caps" / "batch.json")
    assert o["ramps_seed2"]["status"] == "skipped" and o["satin5"]["status"] == "failed"
    assert "holds a different capture (resolution" in o["satin5"]["error"] and "1 failed" in other.stdout
    _hemicube(d, "capture-many", "samples.toml", "-o", "caps")  # the record as the first batch left it


def test_reconstruct_many_reports_the_broken_capture_and_scores_the_rest(batch):
    d, _, recon = batch
    o = _outcomes(d / "out" / "batch.json")
    assert o["broken"]["status"] == "failed" and o["broken"]["attempts"] == 2  # 1 + --retries 1
    assert "manifest" in o["broken"]["error"] and "broken" in recon.stdout
    for name in ("ramps_seed2", "satin5"):
        r = o[name]
        assert r["status"] == "done" and r["attempts"] == 1 and r["seconds"] > 0
        res = r["result"]
        assert res["texels"] == 256 and (res["goals"] == "pass" or res["goals"].endswith("missed"))
        for k in ("alignment.median_px", "maps.normal_deg.median", "maps.alpha_x_pct.median", "render.maps.ssim"):
            assert isinstance(res[k], float), k
        assert (d / "out" / name / "maps").is_dir()
        log = (d / "out" / "logs" / f"{name}.log").read_text()
        assert "--- attempt 1" in log and "[reconstruct] fitting" in log and "--- done in" in log
    broken_log = (d / "out" / "logs" / "broken.log").read_text()
    assert broken_log.count("--- attempt") == 2 and "Traceback" in broken_log
    assert "2 done, 0 skipped (finished before), 1 failed" in recon.stdout


def test_reconstruct_many_skips_finished_and_redoes_changed(batch):
    d, _, _ = batch
    before = _outcomes(d / "out" / "batch.json")
    latent = d / "out" / "satin5" / "latent.exr"
    latent.write_bytes(latent.read_bytes()[:-1] + b"\0")  # changed after it was written
    r = _hemicube(d, "reconstruct-many", "caps", "-o", "out", "--resolution", "16", "--retries", "0", ok=(1,))
    o = _outcomes(d / "out" / "batch.json")
    assert o["ramps_seed2"]["status"] == "skipped" and o["ramps_seed2"]["result"] == before["ramps_seed2"]["result"]
    assert o["satin5"]["status"] == "done"
    assert o["broken"]["status"] == "failed" and o["broken"]["attempts"] == 1
    assert "1 done, 1 skipped (finished before), 1 failed" in r.stdout
    from reconstruction.output import ReconstructionFolder

    assert ReconstructionFolder(d / "out" / "satin5").verify() == []


def test_bad_samples_file_is_one_line(tmp_path):
    (tmp_path / "s.toml").write_text("rig = 'mini'\n[[sample]]\nname = 'ramps'\ncolour = 3\n")
    r = _hemicube(tmp_path, "capture-many", "s.toml", "-o", "caps", ok=(2,))
    assert r.stderr.strip().count("\n") == 0 and "unknown key(s) ['colour']" in r.stderr
    assert not (tmp_path / "caps").exists()


def test_a_batch_that_cannot_start_leaves_nothing(tmp_path):
    (tmp_path / "s.toml").write_text(SAMPLES)
    r = _hemicube(tmp_path, "capture-many", "s.toml", "-o", "caps", "--device", "cuda", ok=(2,))
    assert "GPU tasks asked for, but the Ray cluster has 0 GPUs" in r.stderr and not (tmp_path / "caps").exists()


def test_reconstruct_many_needs_captures(tmp_path):
    (tmp_path / "empty").mkdir()
    r = _hemicube(tmp_path, "reconstruct-many", "empty", "-o", "out", ok=(2,))
    assert "holds no capture folders" in r.stderr and r.stderr.strip().count("\n") == 0


def flaky(marker: str, crash: bool) -> dict:
    """A job that fails its first attempt (raising, or killing its worker process outright) and then works."""
    import os

    m = Path(marker)
    if not m.exists():
        m.write_text("attempted")
        if crash:
            os._exit(3)  # the worker dies: no exception reaches Ray's task
        raise RuntimeError("first attempt fails")
    return {"ok": True}


def test_run_batch_retries_raised_errors_and_dead_workers(tmp_path):
    from ray import cloudpickle

    from twin.batch import BatchOptions, Job, run_batch

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this test module
    jobs = [Job("raises", {"marker": str(tmp_path / "a"), "crash": False}),
            Job("dies", {"marker": str(tmp_path / "b"), "crash": True})]
    out = {o.name: o for o in run_batch(jobs, flaky, options=BatchOptions(num_cpus=2, retries=1, progress=False),
                                        record=tmp_path / "batch.json", logs=tmp_path / "logs")}
    assert out["raises"].status == "done" and out["raises"].attempts == 2
    assert out["dies"].status == "done" and out["dies"].attempts == 2
    rec = json.loads((tmp_path / "batch.json").read_text())["outcomes"]
    assert [o["status"] for o in rec] == ["done", "done"]
    assert "RuntimeError: first attempt fails" in (tmp_path / "logs" / "raises.log").read_text()
    none_left = run_batch(jobs[:1], flaky, options=BatchOptions(num_cpus=1, retries=0, progress=False),
                          done=lambda job: {"from": "before"})
    assert none_left[0].status == "skipped" and none_left[0].result == {"from": "before"}


def sleeper(seconds: float) -> dict:
    """A job that takes `seconds` (a hung device read, a stuck kernel)."""
    time.sleep(seconds)
    return {"slept": seconds}


def test_run_batch_kills_an_attempt_that_runs_over_its_timeout(tmp_path):
    """--timeout: the hung job's worker is killed after each attempt's timeout and the job is reported failed
    after 1 + retries attempts; the job beside it, queued behind it on a one-slot Ray, still runs. An attempt's
    time counts from its submission, so it includes the start of a new worker (the killed one's replacement) and
    its imports (torch's among them), which take several times longer beside the material suite's two processes on
    CI's two cores than on idle ones: the timeout leaves room for that, where one of a few seconds would time the quick
    job out too."""
    from ray import cloudpickle

    from twin.batch import BatchOptions, Job, run_batch

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    jobs = [Job("hangs", {"seconds": 600.0}), Job("quick", {"seconds": 0.1})]
    t0 = time.monotonic()
    out = {o.name: o for o in run_batch(jobs, sleeper, options=BatchOptions(num_cpus=1, retries=1, timeout=45,
                                                                              progress=False),
                                        record=tmp_path / "batch.json")}
    assert time.monotonic() - t0 < 400  # not the 600 s an attempt of the hung job would take
    assert out["hangs"].status == "failed" and out["hangs"].attempts == 2
    assert out["hangs"].error.startswith("TimeoutError: the attempt ran over the batch's timeout of 45 s")
    assert out["quick"].status == "done" and out["quick"].result == {"slept": 0.1}
    with pytest.raises(ValueError, match="timeout must be > 0 seconds"):
        BatchOptions(timeout=0)


"""`hemicube capture-many SAMPLES.toml -o OUT` (docs/scale-out.md): simulated database construction, one Ray task per
sample (twin.batch: local by default, a cluster with --address; GPU tasks on CUDA), skipping finished captures,
retrying failures a bounded number of times.

SAMPLES.toml: top-level keys are defaults for every sample; each [[sample]] names one capture:

    rig = "mini"                 # built-in rig or rig folder (default "mini")
    seed = 1                     # the capture's seed (default 1, as `hemicube capture`)
    sample_resolution = 128      # the built-in samples' map resolution (default 128; `capture --sample-resolution`)
    patterns = "run/patterns.npz"  # learned patterns (a `hemicube train` run's); default: the rig's own
    raw = true                   # also write the raw frames (default false; `capture --raw`)
    [[sample]]
    name = "satin"               # built-in name, NAME@SEED, or a folder of OpenSVBRDF maps
    [[sample]]
    name = "maps/my_leather"     # relative paths are relative to SAMPLES.toml
    seed = 7                     # any default may be set per sample
    folder = "leather_7"         # the capture folder's name under OUT (default: NAME_seedSEED, sanitised)

    OUT/<folder>/   the capture (twin.capture.session; resumed when a run was killed)
    OUT/logs/<folder>.log  what each job printed (progress, a failure's traceback), every attempt
    OUT/batch.json  (twin.batch) one entry per sample: status, attempts, seconds, photos; rewritten as jobs end
A capture is finished when its folder holds the capture the entry describes (the same manifest header) with
every planned photo listed and every file verified; it is then skipped.

The key `resolution`, sample_resolution's old name, is still read for one version, with one line on stderr: elsewhere
--resolution is the texture grid (reconstruct, reconstruct-many), one name with two meanings.
"""
from __future__ import annotations

import sys
import tomllib
from pathlib import Path

from twin.batch import LOG_FOLDER, RECORD_FILE, BatchOptions, Job, outcomes_table, run_batch
from twin.outputs import Kind, claim_output

from .plan import DEFAULT_SEED
from .session import CaptureError, CaptureSession

KEYS = {"name", "rig", "seed", "sample_resolution", "patterns", "raw", "folder"}
DEFAULTS = {"rig": "mini", "seed": DEFAULT_SEED, "sample_resolution": 128, "patterns": None, "raw": False}
# old key -> its new name: read for one version, with one line on stderr
DEPRECATED_KEYS = {"resolution": "sample_resolution"}
# OUT, resumed (twin.outputs): its batch.json names the samples file (reconstruct-many's names its captures)
CAPTURE_MANY_FOLDER = Kind("a capture-many folder", (RECORD_FILE,), field="samples")


def _folder_name(name: str, seed: int) -> str:
    base = Path(name).name if "/" in name else name
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in f"{base}_seed{seed}")


def _renamed(table: dict, where: str, old_used: set) -> dict:
    """`table` with its deprecated keys under their new names (DEPRECATED_KEYS); both names at once are refused."""
    out = dict(table)
    for old, new in DEPRECATED_KEYS.items():
        if old in out:
            if new in out:
                raise ValueError(f"{where}: both {old!r} and {new!r}; keep {new!r} ({old!r} is its deprecated name)")
            out[new] = out.pop(old)
            old_used.add(old)
    return out


def read_samples(path) -> list[dict]:
    """The samples of a SAMPLES.toml with the defaults applied (paths made absolute); one-line errors."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise ValueError(f"{path}: not a readable samples file ({e})") from None
    old_used: set = set()
    top = _renamed({k: v for k, v in doc.items() if k != "sample"}, f"{path}: top level", old_used)
    bad = sorted(set(top) - (KEYS - {"name", "folder"}))
    if bad:
        raise ValueError(f"{path}: unknown top-level key(s) {bad}; allowed: {sorted(DEFAULTS)} and [[sample]]")
    entries = doc.get("sample")
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{path}: no [[sample]] entries")
    here = path.parent
    out, folders = [], set()
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or not isinstance(e.get("name"), str) or not e["name"]:
            raise ValueError(f"{path}: [[sample]] {i + 1} needs a name")
        e = _renamed(e, f"{path}: [[sample]] {i + 1} ({e['name']})", old_used)
        if set(e) - KEYS:
            raise ValueError(f"{path}: [[sample]] {i + 1} ({e['name']}): unknown key(s) {sorted(set(e) - KEYS)}")
        s = {**DEFAULTS, **top, **e}
        if not isinstance(s["seed"], int) or isinstance(s["seed"], bool) or s["seed"] < 0:
            raise ValueError(f"{path}: [[sample]] {i + 1} ({e['name']}): seed must be an integer >= 0")
        r = s["sample_resolution"]
        if not isinstance(r, int) or isinstance(r, bool) or r < 1:
            raise ValueError(f"{path}: [[sample]] {i + 1} ({e['name']}): sample_resolution must be a positive "
                             "integer")
        if not isinstance(s["raw"], bool):
            raise ValueError(f"{path}: [[sample]] {i + 1} ({e['name']}): raw must be true or false")
        for k in ("name", "rig", "patterns"):  # a folder or file named relative to SAMPLES.toml
            v = s[k]
            if isinstance(v, str) and ("/" in v or k == "patterns") and not Path(v).is_absolute():
                s[k] = str(here / v)
        s["folder"] = str(s.get("folder") or _folder_name(e["name"], s["seed"]))
        if s["folder"] in folders or "/" in s["folder"]:
            raise ValueError(f"{path}: [[sample]] {i + 1}: folder {s['folder']!r} is repeated or not a plain name")
        folders.add(s["folder"])
        out.append(s)
    for old in sorted(old_used):  # after the checks: a file refused says only why
        print(f"hemicube capture-many: {path}: key {old!r} is deprecated: use {DEPRECATED_KEYS[old]!r} (the sample's "
              "maps; --resolution is the texture grid in reconstruct)", file=sys.stderr)
    return out


def capture_one(sample: str, rig: str, seed: int, resolution: int, patterns: str | None, raw: bool, output: str,
                device: str) -> dict:
    """A Ray task: run (or resume) one simulated capture; its photo count and the manifest's verdict."""
    import twin
    from twin.capture.runner import capture

    learned = _learned(patterns)
    rig_obj = twin.load_rig(rig)
    if learned is not None:
        learned.check_rig(rig_obj)
    out = capture(rig_obj, sample, output, seed=seed, device=device, resolution=resolution, learned=learned,
                  raw=raw, progress=True)  # to the job's log
    session = CaptureSession.open(out)
    if not session.complete(verify=False):  # the capture checksummed every file as it wrote it
        raise CaptureError(f"{out}: photos of the plan are missing after the capture")
    return _result(session)


def _result(session: CaptureSession) -> dict:
    return {"photos": len(session.photos), "rig": session.rig_name, "seed": session.header["seed"]}


def _learned(patterns: str | None):
    if not patterns:
        return None
    from twin.capture.patterns import load_patterns

    return load_patterns(patterns)


def capture_many(samples_toml, output, device: str = "cpu", options: BatchOptions = BatchOptions()) -> list:
    """Run the batch (module docstring); returns twin.batch.Outcome per sample and writes OUT/batch.json."""
    samples = read_samples(samples_toml)
    out = Path(output)
    claim_output(out, CAPTURE_MANY_FOLDER, [("the samples file", samples_toml)] + [
        (f"the {what} of [[sample]] {i + 1}", s[k]) for i, s in enumerate(samples)
        for k, what in (("name", "maps"), ("rig", "rig folder"), ("patterns", "pattern file"))])
    jobs = [Job(s["folder"], {"sample": s["name"], "rig": s["rig"], "seed": s["seed"],
                              "resolution": s["sample_resolution"], "patterns": s["patterns"], "raw": s["raw"],
                              "output": str(out / s["folder"]), "device": device})
            for s in samples]

    def finished(job: Job):
        """The job's result when its folder holds this very capture (the header capture() would write: rig,
        sample, seed, resolution, patterns, plan, raw frames), finished and verified; else None (the task resumes
        it, or refuses a folder that holds another capture)."""
        import twin
        from twin.capture.runner import capture_header

        a = job.args
        try:
            session = CaptureSession.open(a["output"])
        except CaptureError:
            return None
        try:
            header = capture_header(twin.load_rig(a["rig"]), a["sample"], seed=a["seed"], resolution=a["resolution"],
                                    learned=_learned(a["patterns"]), raw=a["raw"])[0]
        except (ValueError, OSError):  # a bad rig or pattern file: the task runs and reports it
            return None
        return _result(session) if session.holds(header) and session.complete() else None

    return run_batch(jobs, capture_one, done=finished, options=options, record=out / RECORD_FILE,
                     header={"samples": str(samples_toml), "device": device}, logs=out / LOG_FOLDER)


def table(outcomes) -> str:
    return outcomes_table(outcomes, [("rig", "rig"), ("seed", "seed"), ("photos", "photos")])

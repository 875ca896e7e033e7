"""The reconstruction folder (`hemicube reconstruct -o OUT`), and its one owner: the pipeline writes it
through `ReconstructionFolder`, and whoever reads a finished one (validation, a batch over many captures)
reads it here; no other module knows its file names.

    reconstruction.json      format, version, config, network, timings (s) per stage, counts, and the sha256 of
                             every other file ("files"): written last, so a folder is finished when it verifies
    alignment.npz            the alignment map (primary pixel -> secondary pixel) and homography
    measurements.npz         the extracted measurements (reconstruction.stages.extraction.Measurements)
    latent.exr               72 float32 channels L_0 ... L_71 (reference §4: [a_R, a_G, a_B, s])
    latent_passes.npz        the latents after each fine-tuning pass (pass0 ... pass3)
    maps/                    the fitted OpenSVBRDF maps (twin.materials.samples format: pd/ps/ax_ay/normal/
                             tangent/transparency textures, αx ≥ αy)
The pipeline assembles it in a temporary folder that replaces OUT only when complete
(twin.atomic.atomic_folder): a failed or killed run leaves the previous folder, or none.

Finished stages are kept until then in a stage folder beside OUT (`stages_folder`: .OUT.stages/, the same files
as above plus stages.json), so that a killed or failed run resumes after its last finished stage (alignment,
extraction, fine-tuning): stages.json holds, per stage, the key of everything it was computed from (the capture's
content, the rig, the settings, the network) and the sha256 of its files; a stage is reused only when both match.
Its files are hard-linked into the finished folder, and the stage folder is removed once OUT is complete. It is also
where the run keeps its lock (twin.lock) and builds OUT's next version (twin.atomic.atomic_folder's scratch), so that
the next run's clean-up removes what a killed run left there and nothing else.
Fine-tuning and the fit, the long stages at the real device's scale, also keep their unfinished state there
(finetune_state.npz, fit_state.npz and refit_state.npz, the stages "finetune_state", "fit_state" and "refit_state": the
checkpoints of reconstruction.stages.finetune.finetune and reconstruction.stages.fitting.direct._fit_direct, the last
that of the pipeline's refit of the texels next to a brighter highlight), so that a killed one goes on where it stood.

Every file is reached through `_path` (twin.paths.inside): a symbolic link inside either folder is refused by name,
never followed, and so is a path the summary lists outside the folder.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from twin.atomic import atomic_path, file_sha256, write_bytes_atomic
from twin.outputs import Kind
from twin.paths import files_below, inside

FORMAT_NAME = "hemicube-reconstruction"
FORMAT_VERSION = 1
SUMMARY = "reconstruction.json"
ALIGNMENT = "alignment.npz"
MEASUREMENTS = "measurements.npz"
LATENT = "latent.exr"
LATENT_PASSES = "latent_passes.npz"
MAPS = "maps"
STAGES = "stages.json"
FINETUNE_STATE = "finetune_state.npz"
FIT_STATE = "fit_state.npz"
REFIT_STATE = "refit_state.npz"
STAGE_FILES = {"alignment": (ALIGNMENT,), "extraction": (MEASUREMENTS,), "finetune": (LATENT, LATENT_PASSES),
               "finetune_state": (FINETUNE_STATE,), "fit_state": (FIT_STATE,), "refit_state": (REFIT_STATE,)}
PARTIAL_STAGES = ("finetune_state", "fit_state", "refit_state")  # a stage's unfinished state (module docstring)
RECONSTRUCTION_FOLDER = Kind("a reconstruction folder", (SUMMARY,))  # what `reconstruct -o` replaces (twin.outputs)


def _partial(stage: str) -> None:
    if stage not in PARTIAL_STAGES:
        raise ValueError(f"{stage!r} keeps no unfinished state; the stages that do: {PARTIAL_STAGES}")


def stages_folder(out) -> Path:
    """Where `reconstruct` keeps the finished stages of OUT until OUT is complete (module docstring)."""
    out = Path(out)
    return out.with_name(f".{out.name}.stages")


class ReconstructionFolder:
    def __init__(self, directory):
        self.dir = Path(directory)

    def _path(self, rel: str) -> Path:
        return inside(self.dir, rel)

    def _npz(self, name: str, **arrays) -> None:
        with atomic_path(self._path(name), suffix=".npz") as tmp:
            np.savez(tmp, **arrays)

    def write_alignment(self, alignment) -> None:
        self._npz(ALIGNMENT, map=alignment.map, homography=alignment.homography)

    def write_measurements(self, meas) -> None:
        g = meas.grid
        self._npz(MEASUREMENTS, learned=meas.learned, lines=meas.lines, line_weights=meas.line_weights,
                  learned_photos=meas.learned_photos, learned_weights=meas.learned_weights,
                  transparency=meas.transparency, valid=meas.valid, pixel_primary=meas.pixel_primary,
                  pixel_secondary=meas.pixel_secondary, grid=np.array([g.resolution, g.size_mm], np.float64))

    def write_latent(self, latent: np.ndarray, grid_shape, passes: dict) -> None:
        from reconstruction.stages.latents import write_latent_exr

        write_latent_exr(self._path(LATENT), latent, grid_shape)
        self._npz(LATENT_PASSES, **passes)

    def write_maps(self, maps) -> None:
        from twin.materials.samples import write_maps

        write_maps(maps, self._path(MAPS))

    def _files(self) -> list[str]:
        return [rel for rel in files_below(self.dir) if rel != SUMMARY]

    def write_summary(self, summary: dict) -> None:
        """The summary, with the checksums of every file written before it (so: last)."""
        files = {rel: file_sha256(self._path(rel)) for rel in self._files()}
        doc = {"format": FORMAT_NAME, "version": FORMAT_VERSION, **summary, "files": files}
        write_bytes_atomic(self._path(SUMMARY), json.dumps(doc, indent=1).encode())

    def verify(self) -> list[str]:
        """Files that are missing, changed or not listed (empty: a finished, intact reconstruction). A folder
        without a readable summary raises ValueError."""
        listed = self.summary().get("files", {})
        bad = [rel for rel, h in listed.items() if not self._path(rel).is_file() or file_sha256(self._path(rel)) != h]
        return sorted(bad + [rel for rel in self._files() if rel not in listed])

    def summary(self) -> dict:
        path = self._path(SUMMARY)
        try:
            doc = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"{self.dir}: not a finished reconstruction ({path.name}: {e})") from None
        if doc.get("format") != FORMAT_NAME or doc.get("version") != FORMAT_VERSION:
            raise ValueError(f"{path}: not a {FORMAT_NAME} v{FORMAT_VERSION} summary")
        return doc

    # --- stages (module docstring) ---------------------------------------------------------------------
    def _stages(self) -> dict:
        try:
            return json.loads(self._path(STAGES).read_text())
        except (OSError, json.JSONDecodeError, UnicodeDecodeError):
            return {}

    def finished_stage(self, stage: str, key: str) -> dict | None:
        """The record (its `extra`) of `stage` when it was finished with `key` and its files still verify; else
        None."""
        rec = self._stages().get(stage)
        if not isinstance(rec, dict) or rec.get("key") != key:
            return None
        files = rec.get("files", {})
        if sorted(files) != sorted(STAGE_FILES[stage]):
            return None
        if any(not self._path(f).is_file() or file_sha256(self._path(f)) != h for f, h in files.items()):
            return None
        return rec.get("extra", {})

    def record_stage(self, stage: str, key: str, extra: dict) -> None:
        """Mark `stage` finished with `key` (its files written before), with the sha256 of its files."""
        doc = self._stages()
        doc[stage] = {"key": key, "files": {f: file_sha256(self._path(f)) for f in STAGE_FILES[stage]}, "extra": extra}
        write_bytes_atomic(self._path(STAGES), json.dumps(doc, indent=1).encode())

    def forget_stage(self, stage: str) -> None:
        """Remove a stage's record and files (an unfinished stage's state once the stage has finished)."""
        doc = self._stages()
        if doc.pop(stage, None) is not None:
            write_bytes_atomic(self._path(STAGES), json.dumps(doc, indent=1).encode())
        for f in STAGE_FILES[stage]:
            self._path(f).unlink(missing_ok=True)

    def link_stage(self, stage: str, dest: "ReconstructionFolder") -> None:
        """Hard-link the stage's files into `dest` (copied where the file system has no hard links)."""
        import shutil

        for f in STAGE_FILES[stage]:
            try:
                os.link(self._path(f), dest._path(f))
            except OSError:
                shutil.copy2(self._path(f), dest._path(f))

    def alignment(self, info: dict):
        """The alignment written by write_alignment, with its `info` (kept in the stage record)."""
        from reconstruction.stages.alignment import Alignment

        with np.load(self._path(ALIGNMENT), allow_pickle=False) as z:
            return Alignment(z["map"], z["homography"], info)

    def measurements(self):
        """The measurements written by write_measurements."""
        from reconstruction.stages.extraction import Measurements, TextureGrid

        with np.load(self._path(MEASUREMENTS), allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        res, size = a.pop("grid")
        a.pop("learned")  # kept for readers of the file; Measurements derives it from the photos
        return Measurements(grid=TextureGrid(int(res), float(size)), **a)

    def latent_passes(self) -> dict:
        """pass0 ... pass3 -> (N, 72) latents, as write_latent wrote them."""
        with np.load(self._path(LATENT_PASSES), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}

    def write_state(self, stage: str, state: dict) -> None:
        """An unfinished stage's state (PARTIAL_STAGES; a dict of numpy arrays, JSON-able values and such dicts):
        the arrays by their dotted names, the rest as JSON in `__meta__`."""
        _partial(stage)
        arrays = {}

        def split(d: dict, prefix: str) -> dict:
            out = {}
            for k, v in d.items():
                if isinstance(v, np.ndarray):
                    arrays[prefix + k] = v
                else:
                    out[k] = split(v, f"{prefix}{k}.") if isinstance(v, dict) else v
            return out

        meta = json.dumps(split(state, "")).encode()
        self._npz(STAGE_FILES[stage][0], __meta__=np.frombuffer(meta, dtype=np.uint8), **arrays)

    def state(self, stage: str) -> dict:
        """The state written by write_state."""
        _partial(stage)
        with np.load(self._path(STAGE_FILES[stage][0]), allow_pickle=False) as z:
            state = json.loads(z["__meta__"].tobytes())
            for name in z.files:
                if name != "__meta__":
                    *path, leaf = name.split(".")
                    d = state
                    for k in path:
                        d = d.setdefault(k, {})
                    d[leaf] = z[name]
        return state

    def maps(self):
        from twin.materials.samples import read_maps

        folder = self._path(MAPS)
        files_below(folder)  # a link inside maps/ is refused too
        return read_maps(folder)

    def latent(self) -> np.ndarray:
        """(R, C, 72) float32 final latents."""
        from reconstruction.stages.latents import read_latent_exr

        return read_latent_exr(self._path(LATENT))

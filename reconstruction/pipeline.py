"""The reconstruction pipeline (`hemicube reconstruct`): a capture folder in, OpenSVBRDF maps and latents out.

The same code runs on a folder from the twin or from the real device (it reads only the photos, the
patterns the LEDs showed and the rig folder the capture carries; the ground truth, when present, is left
to `reconstruction.evaluation.validation`).

    1. alignment       secondary -> primary, uniform-light photos (reconstruction.stages.alignment; paper §8)
    2. extraction      texture grid + per-texel measurements (reconstruction.stages.extraction; reference §6.1, §6.3)
    3. decode          encoder -> 56-D latent per texel (reconstruction.stages.latents; paper §7)
    4. fine-tuning     three passes against the line photos, one held out (reconstruction.stages.finetune; §7.1), and
                       optionally the learned-pattern photos (ReconstructConfig.finetune_photos)
    5. fitting         GGX + local frame per texel against the decoded lumitexels (reconstruction.stages.fitting; §7.2);
                       then the texels next to a much brighter highlight fitted again from sharper photos
                       (ReconstructConfig.spill_ratio, spill_texels; ours, docs/accuracy.md)

The output folder is reconstruction.output.ReconstructionFolder (its file names live there alone); an existing
path that is not one, or an output inside the capture, is refused before any work (`check_output`); an output that
is a symbolic link (a folder on a scratch disk) is written where it points. Stages 1, 2 and 4 are kept as they
finish, so a killed or failed run, started again with the same capture and settings, resumes after the last one
finished (reconstruction.output's stage folder). One run at a time holds the stage folder's lock (twin.lock); a run
refused it changes nothing there. Every setting is checked against the capture before the lock is taken
(`check_settings`): a bad one costs no work and leaves nothing behind.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from reconstruction.stages.alignment import AlignConfig
from reconstruction.stages.alignment_check import CheckConfig
from reconstruction.stages.finetune import FinetuneConfig
from reconstruction.stages.fitting import FitConfig
from reconstruction.output import RECONSTRUCTION_FOLDER, STAGES, ReconstructionFolder, stages_folder

FINETUNE_PHOTOS = ("lines", "lines+learned")


@dataclass(frozen=True)
class ReconstructConfig:
    """The pipeline's settings, `hemicube reconstruct`'s options (each field's comment says why its default):

    resolution        texels a side of the square texture grid: the maps are resolution x resolution
    size_mm           the grid's side in mm (None: detected from the photos, reference §6.1)
    holdout_line      index of the line photo left out of fine-tuning (None: the brightest over the sample)
    footprint         how a texel's value is read from the photos' pixels: "cell", "point" or "gaussian"
    finetune_photos   "lines" or "lines+learned": the photos fine-tuning fits
    spill_ratio       a ratio > 1 of a neighbour's specular peak to a texel's own above which the texel is fitted
                      again from demosaiced photos (None: never)
    network           "pretrained" (the network shipped for the capture's rig) or a `hemicube train` run folder
    device            "cpu", "cuda" or "cuda:N"
    align, alignment_check, finetune, fit   each stage's own settings (their classes in reconstruction.stages)
    accept_alignment  go on when the alignment check flags the alignment
    A bad footprint, finetune_photos or spill_ratio is a ValueError when the config is made; the others are checked
    against the capture before any work (check_settings)."""

    # texels per side of the texture grid; the paper reconstructs 1024 x 1024 (reference §6.1). 48 is this
    # project's default for the mini rig on a CPU (its 120 mm sample spans ~110 primary pixels: ~2 px a texel)
    resolution: int = 48
    size_mm: float | None = None   # side of the texture grid; None: detected (reference §6.1, 6.5% shrink)
    # the line photo left out of fine-tuning for validation (the paper holds out 1 of 64, unnamed);
    # None: the brightest line over the sample (a dim line would score the sensor's noise, not the model)
    holdout_line: int | None = None
    # how a texel's photo value is read: "cell" (the mean over the photosites of its cell: where a texel spans
    # many, their noise is what decides a weak lobe), "point" (at its centre) or "gaussian" (the reference's
    # anti-aliasing blur); reconstruction.stages.extraction, step 2
    footprint: str = "cell"
    # the photos fine-tuning fits (step 4): "lines" (the 64 linear lights less the held-out one, as the paper and
    # the reference) or "lines+learned" (and the primary view's learned-pattern photos, which light many LEDs at
    # once: they constrain directions of the latent that no line sees; docs/accuracy.md)
    finetune_photos: str = "lines"
    # the texels that a neighbour's much brighter highlight spills into (ours): a texel with an 8-neighbour
    # whose fitted specular peak mean(rho_s) / (alpha_x alpha_y) exceeds this many times its own is fitted again with
    # its photos, in both views, demosaiced by Malvar-He-Cutler 2004 (reconstruction.stages.extraction, step 0). The bilinear
    # demosaic gives ~0.2 of a neighbour's red or blue light to a texel 2.2 px away (docs/accuracy.md), so from about
    # 1 / 0.2 times the texel's own peak the spill is as large as the texel's own highlight. None: never
    spill_ratio: float | None = 4.0
    network: str = "pretrained"    # "pretrained" (shipped for this rig) or a `hemicube train` run folder
    device: str = "cpu"
    align: AlignConfig = field(default_factory=AlignConfig)
    # the alignment's check without ground truth (reconstruction.stages.alignment_check): a flagged alignment stops
    # the reconstruction with one line, unless accept_alignment (the stage is kept: a re-run resumes from it)
    alignment_check: CheckConfig = field(default_factory=CheckConfig)
    accept_alignment: bool = False
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)
    fit: FitConfig = field(default_factory=FitConfig)

    def __post_init__(self):
        from reconstruction.stages.extraction import FOOTPRINTS

        if self.footprint not in FOOTPRINTS:
            raise ValueError(f"ReconstructConfig.footprint must be one of {tuple(FOOTPRINTS)}, got {self.footprint!r}")
        if self.spill_ratio is not None and not (isinstance(self.spill_ratio, (int, float))
                                                 and math.isfinite(self.spill_ratio) and self.spill_ratio > 1):
            raise ValueError(f"ReconstructConfig.spill_ratio must be a number > 1 or None, got {self.spill_ratio!r}")
        if self.finetune_photos not in FINETUNE_PHOTOS:
            raise ValueError(f"ReconstructConfig.finetune_photos must be one of {FINETUNE_PHOTOS}, "
                             f"got {self.finetune_photos!r}")


@dataclass
class Reconstruction:
    directory: Path
    measurements: object      # reconstruction.stages.extraction.Measurements (its .grid is the texture grid)
    latent: np.ndarray        # (N, 72) final latents
    maps: object              # twin.materials.samples.SVBRDFMaps
    holdout_line: int
    timings: dict
    alignment: object
    model: object

    @property
    def grid(self):
        return self.measurements.grid


def load_network(name: str, rig, device="cpu"):
    """The acquisition network: the one shipped for `rig` ("pretrained") or a `hemicube train` run folder."""
    if name == "pretrained":
        from twin.rig.builtin import serves_for

        from reconstruction.network.shipped import load_pretrained, pretrained_info

        info = pretrained_info(rig.name)
        if info is None or not serves_for(rig, info["rig_digest"]):  # a vignetting calibration keeps the network
            raise ValueError(f"no network ships for rig {rig.name!r}; train one (`hemicube train --rig ...`) and "
                             "pass its run folder (--network RUN)")
        return load_pretrained(rig.name, device)[0]
    from reconstruction.network.train import load_run_model

    return load_run_model(name, device)


def choose_holdout(lines: np.ndarray, valid: np.ndarray) -> int:
    """The line whose median texel value (mean RGB) over the valid texels is the largest."""
    return int(np.argmax(np.median(lines[valid].mean(axis=2), axis=0)))


def network_input(network: str) -> tuple[str, str | None]:
    """The network a reconstruction reads, as an input its output must stay out of (twin.outputs.claim_output): a
    `hemicube train` run folder; the shipped one ("pretrained") lies in the package, no output's concern."""
    return "the network's run folder", None if network == "pretrained" else network


def check_output(out: Path, capture: Path, network: str = "pretrained") -> None:
    """An output folder is owned, never clobbered (twin.outputs): `reconstruct` replaces only a reconstruction
    folder (its summary file names it) or an empty folder, and never writes into, over or around the capture it
    reads or the network run folder it decodes with. A ValueError names the path otherwise, before anything is
    written."""
    from twin.outputs import claim_output

    claim_output(out, RECONSTRUCTION_FOLDER, [("the capture being read", capture), network_input(network)])


def check_settings(config: ReconstructConfig, session, rig):
    """Every setting checked against the capture and its rig before any work (no lock taken, no stage folder made):
    the device exists, the texture grid fits the rig (reconstruction.stages.extraction.TextureGrid.check_rig; with
    the detected size, the largest sample the rig holds), the held-out line is one of the capture's, and the network
    loads and was trained with the capture's learned patterns. A ValueError says which setting otherwise."""
    from twin.capture.plan import indices_of
    from twin.optics.inputs import check_device

    from reconstruction.stages.extraction import TextureGrid
    from reconstruction.stages.latents import check_patterns

    check_device(config.device)
    TextureGrid(config.resolution, rig.sample.max_size if config.size_mm is None else config.size_mm).check_rig(rig)
    lines = len(indices_of(session).lines)
    if config.holdout_line is not None and not (isinstance(config.holdout_line, (int, np.integer))
                                                and 0 <= config.holdout_line < lines):
        raise ValueError(f"--holdout-line {config.holdout_line}: the capture has {lines} line photos, 0 to "
                         f"{lines - 1}")
    # the decode loads the network again, where it always has: fine-tuning on a copy loaded before the alignment gave
    # other bits than the same run in another process (tests/reconstruction/test_reconstruct_resume.py)
    check_patterns(load_network(config.network, rig, config.device), session, rig)


def reconstruct(capture, output, config: ReconstructConfig = ReconstructConfig(), *, progress: bool = True,
                rig=None, break_lock: bool = False) -> Reconstruction:
    """Run the pipeline on a capture folder into `output` (module docstring). `break_lock`: take the stage folder's
    lock that another host recorded (twin.lock).

    capture    a capture folder (twin.capture.session: `hemicube capture`'s, or the real device's)
    output     the reconstruction folder to write (reconstruction.output), a path
    rig        the rig to reconstruct with (default: the rig folder the capture carries; lengths in mm)
    progress   each stage's progress on stderr
    Returns a Reconstruction with R = config.resolution: directory (`output`), measurements (its .grid: R x R
    texels over grid.size_mm mm, texel_mm each), latent (R * R, 72), maps (twin.materials.samples.SVBRDFMaps
    on that grid: rho_d (R, R, 3) in [0, 1], rho_s (R, R, 3), alpha (R, R, 2) GGX roughness, normal and tangent
    (R, R, 3) unit vectors in the world frame, transparency (R, R)), holdout_line, timings ({stage}_s in seconds),
    alignment (primary pixel -> secondary pixel) and model (the network that decoded it). A bad setting or
    capture is a ValueError before any work."""
    from twin.atomic import atomic_folder, remove_leftovers
    from twin.capture.session import CaptureSession
    from twin.lock import FolderLock
    from twin.paths import files_below, inside

    session, out = CaptureSession.open(capture), Path(output)
    check_output(out, session.dir, config.network)
    if rig is None:
        rig = session.rig()
    check_settings(config, session, rig)
    target = Path(os.path.realpath(out)) if out.is_symlink() else out
    # the stage folder is no link, nor is anything in it: refused before the lock, so a refused run leaves it as it is
    stages = ReconstructionFolder(inside(target.parent, stages_folder(target).name))
    files_below(stages.dir)
    lock = FolderLock(stages.dir, "another reconstruction", shown=out).acquire(break_lock)
    finished = False
    try:
        remove_leftovers(stages.dir)  # a killed run's half-built OUT and temporary files (the lock is ours now)
        # a failed run leaves the previous folder (or none)
        with atomic_folder(target, overwrite=True, scratch=stages.dir) as tmp:
            recon = _reconstruct_into(ReconstructionFolder(tmp), stages, session, rig, config, progress)
        finished = True
    finally:
        if finished or not (stages.dir / STAGES).exists():  # OUT holds the stages' files now, or none was finished
            lock.remove_folder()
        else:
            lock.release()
    recon.directory = out
    return recon


def _photos(meas, learned: bool, lines=slice(None)) -> tuple[np.ndarray, np.ndarray]:
    """(N, K, 3) photos and their (K, L, 3) patterns: the `lines` chosen, then, if `learned`, the primary view's
    learned-pattern photos (the same units: both are measurements of the decoder's lumitexel)."""
    photos, weights = meas.lines[:, lines], meas.line_weights[lines]
    if not learned:
        return photos, weights
    return (np.concatenate([photos, meas.learned_photos[:, 0]], axis=1),
            np.concatenate([weights, meas.learned_weights], axis=0))


SPILL_DEMOSAIC = "malvar2004"  # the refit's demosaic (ReconstructConfig.spill_ratio)


def spill_texels(fit, grid_shape, ratio: float) -> np.ndarray:
    """(R, C) bool: the texels of a fit (reconstruction.stages.fitting.FitResult, row-major on the grid) with an 8-neighbour
    whose specular peak mean(rho_s) / (alpha_x alpha_y) (GGX's D at the half vector, times rho_s) exceeds `ratio`
    times their own (ReconstructConfig.spill_ratio)."""
    peak = (np.asarray(fit.rho_s, np.float64).mean(axis=1)
            / (np.asarray(fit.alpha_x, np.float64) * np.asarray(fit.alpha_y, np.float64))).reshape(grid_shape)
    R, C = peak.shape
    padded = np.pad(peak, 1)  # zeros beyond the grid: no neighbour there
    brightest = np.max([padded[1 + dr:1 + dr + R, 1 + dc:1 + dc + C]
                        for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc], axis=0)
    return brightest > ratio * peak


def _key(*parts) -> str:
    """A stage's key: sha256 of what it is computed from (the previous stage's key first)."""
    return hashlib.sha256(json.dumps(_jsonable(parts), sort_keys=True).encode()).hexdigest()


def _network_digest(model) -> str:
    """sha256 of the network's parameters and buffers, in state_dict order."""
    h = hashlib.sha256()
    for name, t in model.state_dict().items():
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _reconstruct_into(out: ReconstructionFolder, stages: ReconstructionFolder, session, rig,
                      config: ReconstructConfig, progress: bool) -> Reconstruction:
    from twin.capture.plan import indices_of

    from reconstruction.stages.alignment import AlignmentError, align_views
    from reconstruction.stages.alignment_check import check_alignment
    from reconstruction.stages.extraction import extract, texture_grid
    from reconstruction.stages.finetune import decoded_lumitexels, finetune
    from reconstruction.stages.fitting import fit_ggx, to_maps
    from reconstruction.stages.latents import decode

    timings: dict[str, float] = {}
    resumed: list[str] = []

    def stage(name):
        if progress:
            print(f"[reconstruct] {name} ...", flush=True)
        return time.perf_counter()

    def finished(name, key, *needs):
        """The stage's record when a run before this one finished it with this key (then reused), else None (also
        when the record lacks what this run needs from it)."""
        rec = stages.finished_stage(name, key)
        if rec is not None and all(k in rec for k in ("seconds", *needs)):
            resumed.append(name)
            timings[f"{name}_s"] = rec["seconds"]
            if progress:
                print(f"[reconstruct] {name}: resumed from {stages.dir}", flush=True)
            return rec
        return None

    def done(name, key, t, earlier=0.0, **extra):
        timings[f"{name}_s"] = time.perf_counter() - t + earlier
        stages.record_stage(name, key, {"seconds": timings[f"{name}_s"], **_jsonable(extra)})

    key = _key(session.content_digest(), rig.digest(), config.device, asdict(config.align),
               asdict(config.alignment_check))
    rec = finished("alignment", key, "info")
    if rec is not None:
        alignment = stages.alignment(rec["info"])
    else:
        t = stage("alignment")
        uniform = indices_of(session).uniform
        pair = session.photo(uniform, 0), session.photo(uniform, 1)
        alignment = align_views(*pair, rig, replace(config.align, device=config.device))
        alignment.info["check"] = check_alignment(*pair, alignment, rig, config.alignment_check)
        stages.write_alignment(alignment)
        done("alignment", key, t, info=alignment.info)
    stages.link_stage("alignment", out)
    check = alignment.info["check"]
    if check["flagged"] and not config.accept_alignment:
        raise AlignmentError(
            f"alignment: after aligning, the two views still disagree by {check['median_shift_px']:.2f} px (median "
            f"over {check['tiles_used']} tiles; limit {check['flag_px']} px): has a camera moved since calibration, or "
            "is the sample off the board? Re-run with --accept-alignment to go on with this alignment")

    key = _key(key, config.resolution, config.size_mm, config.footprint)
    if finished("extraction", key) is not None:
        meas = stages.measurements()
        grid = meas.grid
    else:
        t = stage("extraction")
        grid = texture_grid(session, rig, config.resolution, config.size_mm)
        meas = extract(session, rig, grid, alignment, footprint=config.footprint, progress=progress)
        if not meas.valid.all():  # the grid lies inside the sample, which both views see whole
            raise ValueError(f"{session.dir}: {int((~meas.valid).sum())} of the {grid.resolution}^2 texels are not "
                             "seen by both cameras (or their photos are not finite); choose a smaller --size-mm")
        stages.write_measurements(meas)
        done("extraction", key, t)
    stages.link_stage("extraction", out)

    t = stage("decode")
    model = load_network(config.network, rig, config.device)
    hold = choose_holdout(meas.lines, meas.valid) if config.holdout_line is None else int(config.holdout_line)
    ft_cfg = _with_holdout(config.finetune, hold, config.device)
    key = _key(key, _network_digest(model), asdict(ft_cfg), config.finetune_photos)
    rec = finished("finetune", key, "finetune")
    if rec is None:  # the decoded latents are fine-tuning's start; a resumed run needs only the network
        z56 = decode(model, meas.learned, device=config.device)
    timings["decode_s"] = time.perf_counter() - t
    if rec is not None:
        latent = stages.latent_passes()["pass3"]  # FinetuneResult.latent is the pass-3 latent
        ft_info = rec["finetune"]
    else:
        t = stage(f"fine-tuning (line {hold} held out)")
        checkpoint = _Checkpoint(stages, "finetune_state", key)
        # the lines come first, so the held-out index is the same in both sets
        ft = finetune(model, z56, *_photos(meas, config.finetune_photos == "lines+learned"), ft_cfg,
                      checkpoint=checkpoint, progress=progress)
        latent, ft_info = ft.latent, {"iterations": ft.iterations, "seconds": ft.seconds}
        stages.write_latent(latent, grid.shape, ft.passes)
        done("finetune", key, t, checkpoint.earlier, finetune=ft_info)
        stages.forget_stage("finetune_state")
        if checkpoint.loaded is not None:
            resumed.append(f"finetune ({checkpoint.loaded})")
    stages.link_stage("finetune", out)

    t = stage("fitting")
    # decoded chunk by chunk as the fit goes (a paper-rig grid's lumitexels do not fit in memory at once), in the
    # fine-tuning's precision
    lumi = decoded_lumitexels(model, latent, precision=ft_cfg.precision)
    keep = [k for k in range(meas.lines.shape[1]) if k not in ft_cfg.holdout]  # the held-out line stays unseen
    # the fit's measured photos (ours): the kept lines and the 64 learned-pattern photos of the primary
    # view, and those of the secondary view: the learned patterns light many LEDs at once, so they sample narrow
    # lobes between the lines, and the 45-degree view sees the grazing half-angles where Fresnel lifts a weak
    # specular lobe (docs/accuracy.md: ceramic alpha 21% -> 12% with the primary photos, ...)
    photos, weights = _photos(meas, True, keep)
    # the photos' weight against the lumitexels (FitConfig.lambda_lines) was measured on photos of one frame an
    # exposure; the HDR merge of F frames divides their temporal noise's variance by F while the decoder's error in
    # the lumitexels stays, so, as an inverse-variance weight, it scales by F (with four frames, every
    # suite sample's alpha median improves or holds, docs/accuracy.md)
    fit_cfg = replace(config.fit, device=config.device,
                      lambda_lines=config.fit.lambda_lines * session.frames_per_exposure)
    direct = fit_cfg.method == "direct"  # the method that keeps a checkpoint and refits from the first fit's numbers
    checkpoint = _Checkpoint(stages, "fit_state", _key(key, asdict(fit_cfg)))
    fit = fit_ggx(rig, grid.positions(rig), lumi, lines=photos, line_weights=weights,
                  secondary=(meas.learned_photos[:, 1], meas.learned_weights), grid_shape=grid.shape,
                  config=fit_cfg, checkpoint=checkpoint if direct else None, progress=progress)
    timings["fitting_s"] = time.perf_counter() - t + checkpoint.earlier
    if checkpoint.loaded is not None:
        resumed.append(f"fitting ({checkpoint.loaded})")
    # the refit fits the texels next to a brighter highlight again from their own initial candidates: started from
    # the first fit's numbers instead, paper's flat alpha landscape kept them in the first fit's basins (alpha
    # 11.5 / 12.9% against 8.5 / 9.2%, docs/accuracy.md); every other texel keeps its own numbers (its photos are
    # the same), and the neighbour propagation and the joint priors run again over all (_fit_direct's start)
    spill = np.zeros(grid.shape, bool) if config.spill_ratio is None else spill_texels(fit, grid.shape,
                                                                                       config.spill_ratio)
    if spill.any():
        t = stage(f"refit of {int(spill.sum())} texels next to a brighter highlight ({SPILL_DEMOSAIC} photos)")
        sharp = extract(session, rig, grid, alignment, footprint=config.footprint, demosaic=SPILL_DEMOSAIC)
        on = spill.reshape(-1, 1, 1)
        photos = np.where(on, _photos(sharp, True, keep)[0], photos)
        secondary = np.where(on, sharp.learned_photos[:, 1], meas.learned_photos[:, 1])
        checkpoint = _Checkpoint(stages, "refit_state", _key(key, asdict(fit_cfg), config.spill_ratio))
        fit = fit_ggx(rig, grid.positions(rig), lumi, lines=photos, line_weights=weights,
                      secondary=(secondary, meas.learned_weights), grid_shape=grid.shape, config=fit_cfg,
                      checkpoint=checkpoint if direct else None,
                      start=(fit.info["texel_q"], spill.reshape(-1)) if direct else None, progress=progress)
        timings["refit_s"] = time.perf_counter() - t + checkpoint.earlier
        if checkpoint.loaded is not None:
            resumed.append(f"refit ({checkpoint.loaded})")
    maps = to_maps(fit, grid.shape, grid.size_mm, meas.transparency.reshape(grid.shape),
                   name=f"reconstruction of {session.sample}")
    out.write_maps(maps)

    summary = {"capture": str(session.dir),
               "rig": rig.name, "rig_digest": rig.digest(), "config": _jsonable(asdict(config)),
               "grid": {"resolution": grid.resolution, "size_mm": grid.size_mm},
               "texels": int(meas.valid.size), "holdout_line": hold, "spill_texels": int(spill.sum()),
               "timings_s": timings,
               "finetune": _jsonable(ft_info), "resumed": resumed,
               "fit": _jsonable({k: v for k, v in fit.info.items() if k not in ("texel_loss", "texel_q")}),
               "alignment": _jsonable(alignment.info)}
    out.write_summary(summary)
    return Reconstruction(out.dir, meas, latent, maps, hold, timings, alignment, model)


class _Checkpoint:
    """A long stage's unfinished state in the stage folder under that stage's key (the checkpoints of
    reconstruction.stages.finetune.finetune and reconstruction.stages.fitting.direct._fit_direct; the files are
    reconstruction/output.py's, the stages output.PARTIAL_STAGES). `loaded`: the phase a killed run had reached, if
    any; `earlier`: the seconds the runs before this one had spent on the stage up to their last save (0 when none),
    which the stage's timing adds, so that a stage resumed across calls reports the time its result took, not this
    call's share."""

    def __init__(self, stages: ReconstructionFolder, stage: str, key: str):
        self.stages, self.stage, self.key, self.loaded, self.earlier = stages, stage, key, None, 0.0
        self._started = time.perf_counter()

    def load(self) -> dict | None:
        rec = self.stages.finished_stage(self.stage, self.key)
        if rec is None:
            return None
        state = self.stages.state(self.stage)
        spent = rec.get("seconds")  # a timing only: a record without a sound one counts from now
        self.loaded = state.get("phase")
        self.earlier = float(spent) if isinstance(spent, (int, float)) and np.isfinite(spent) and spent >= 0 else 0.0
        return state

    def save(self, state: dict) -> None:
        self.stages.write_state(self.stage, state)
        self.stages.record_stage(self.stage, self.key, {
            "phase": state["phase"], "seconds": self.earlier + time.perf_counter() - self._started})


def _with_holdout(cfg, hold: int, device):
    return replace(cfg, holdout=tuple(sorted(set(cfg.holdout) | {hold})), device=device)


def _jsonable(x):
    return json.loads(json.dumps(x, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))

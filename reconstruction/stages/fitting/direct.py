"""The "direct" method (paper §7.2; ours), in order: each chunk of texels from its best initial candidate
(reconstruction.stages.fitting.candidates) by Levenberg-Marquardt (reconstruction.stages.fitting.solver); on a grid,
neighbour propagation and the joint prior (reconstruction.stages.fitting.joint). The fit keeps its state in a
checkpoint as it goes, so that a killed one resumes to the same numbers, and refits only the texels whose photos
changed when given an earlier fit's numbers (the pipeline's refit of the texels next to a brighter highlight).
"""
from __future__ import annotations

import time

import numpy as np
import torch

from twin.progress import progress_bar

from reconstruction.stages.fitting.candidates import _initial
from reconstruction.stages.fitting.config import GEOMETRY_SIZE, FitResult
from reconstruction.stages.fitting.geometry import _geometry, _log_geometry
from reconstruction.stages.fitting.joint import _joint_albedos, _joint_roughness
from reconstruction.stages.fitting.model import _projected_loss
from reconstruction.stages.fitting.problem import _chunk_size, _chunks, _Problem, _result
from reconstruction.stages.fitting.solver import _levenberg_marquardt, _propagate


# how often the direct fit's chunks save their state to a checkpoint (ours): a 1024^2 paper-rig fit takes minutes,
# a save of its numbers (5 floats a texel) a fraction of a second
CHECKPOINT_SECONDS = 30.0


def _fit_direct(prob: _Problem, grid_shape=None, checkpoint=None, start=None,
                progress: bool = False) -> FitResult:
    """Levenberg-Marquardt on the 5 geometry numbers per texel from the best initial candidate, with the
    albedos in closed form at every evaluation (reconstruction.stages.fitting.model), in chunks of `batch` texels;
    then, on a grid (grid_shape given), FitConfig.propagation rounds of neighbour propagation (_propagate), and the
    joint prior (reconstruction.stages.fitting.joint).
    info's texel_q holds the per-texel numbers before the joint prior (what a refit starts from).

    start: None, or a refit (q, redo) of the same texels after the photos of some changed: q (N, 5) an earlier
    fit's texel_q, redo (N,) bool the texels whose photos changed. Only those are fitted again, from their own
    initial candidates; every other texel keeps its numbers, which its unchanged photos would give again, and the
    propagation's first round starts from the refitted texels (ours: the pipeline's refit of the texels next to a
    brighter highlight touches a few % of them, and would otherwise be a whole second fit).

    checkpoint: None, or an object with load() -> dict | None and save(dict) where the fit keeps its state as it
    goes: the numbers of the chunks fitted so far (at most every CHECKPOINT_SECONDS), after each propagation round,
    and after each step of the joint prior. A fit given the state a killed one saved goes on from there and ends
    with the same numbers as one that was never stopped (each chunk's fit depends on its own texels only, and the
    later phases on the numbers saved); the state's arrays are numpy, the rest JSON-able. progress: a bar over the
    Levenberg-Marquardt iterations of the chunks and the joint prior's trials (twin.progress: on a terminal only)."""
    t_start = time.perf_counter()
    c = prob.config
    redo = None
    if start is not None:
        q_start, redo = np.asarray(start[0], np.float32), np.asarray(start[1])
        if q_start.shape != (prob.n, GEOMETRY_SIZE) or redo.shape != (prob.n,) or redo.dtype != bool \
                or not np.isfinite(q_start).all():
            raise ValueError(f"a refit's start must be an earlier fit's finite texel_q ({prob.n}, {GEOMETRY_SIZE}) "
                             f"and a boolean mask ({prob.n},) of the texels to fit again")
        redo = torch.as_tensor(redo, device=prob.pos.device)
    refitted = None if redo is None else int(redo.sum())
    state = _resumed(checkpoint, prob)
    if state is not None and state.get("refitted") != refitted:
        # another kind of fit's state under this key: a refit's saved before refits kept the other texels' numbers
        # (its chunks covered every texel), or a whole fit's; a refit takes seconds, so it starts again
        state = None
    if state is None:
        state = {"phase": "chunks", "chunks_done": 0,
                 "q": np.zeros((prob.n, GEOMETRY_SIZE), np.float32) if start is None else q_start.copy(),
                 "history": np.zeros(c.steps), "restarted": [], "refitted": refitted,
                 "seconds": {"init": 0.0, "iterations": 0.0, "propagation": 0.0, "joint": 0.0}}
    seconds = state["seconds"]
    history = np.array(state["history"], dtype=np.float64)
    q = torch.as_tensor(np.asarray(state["q"], np.float32), device=prob.pos.device)

    def save(**changes):
        if checkpoint is not None:
            state.update(changes, q=q.cpu().numpy(), history=history.copy(), seconds=seconds)
            checkpoint.save(state)

    last_save = time.perf_counter()
    chunks = _chunks(prob, c.batch) if redo is None else \
        [k for k in torch.nonzero(redo).flatten().split(_chunk_size(prob, c.batch)) if k.numel()]
    joint = grid_shape is not None and c.alpha_prior is not None
    first = state["chunks_done"] if state["phase"] == "chunks" else len(chunks)
    bar = progress_bar(total=len(chunks) * c.steps + (c.steps if joint else 0), initial=first * c.steps,
                       desc="fitting", unit="step", enabled=progress)
    for k in range(first, len(chunks)):
        idx = chunks[k]
        part = prob.part(idx)
        t0 = time.perf_counter()
        with torch.no_grad():
            g = _initial(part)[0]
            geom = _geometry(g, part.frame, c)
            q0 = torch.cat([g[:, :3], torch.log(geom["alpha_x"])[:, None], torch.log(geom["alpha_y"])[:, None]], 1)
        t1 = time.perf_counter()
        seconds["init"] += t1 - t0
        q[idx] = _levenberg_marquardt(part, q0, history, tick=lambda: bar.update(1))
        seconds["iterations"] += time.perf_counter() - t1
        if time.perf_counter() - last_save >= CHECKPOINT_SECONDS or k == len(chunks) - 1:
            save(chunks_done=k + 1, phase="chunks" if k < len(chunks) - 1 else "propagation")
            last_save = time.perf_counter()
    restarted = state["restarted"]
    if state["phase"] in ("chunks", "propagation"):
        changed = state.get("changed")  # None: the first round, or a checkpoint saved before rounds kept it
        # the first round tries every texel, a refit's only those next to the texels it fitted again
        changed = torch.as_tensor(np.asarray(changed), device=q.device) if restarted and changed is not None else redo
        for _ in range(c.propagation - len(restarted) if grid_shape is not None else 0):
            if (restarted and not restarted[-1]) or (changed is not None and not bool(changed.any())):
                break  # the last round moved nothing, or a refit fitted nothing again
            t2 = time.perf_counter()
            q, moved, changed = _propagate(prob, q, grid_shape, changed)
            restarted.append(moved)
            seconds["propagation"] += time.perf_counter() - t2
            save(restarted=restarted, changed=changed.cpu().numpy())
    t3 = time.perf_counter()
    texel_q = q.cpu().numpy().copy()
    parts = _final(prob, q)
    prior = {}
    joint_before = seconds["joint"]
    if joint:
        def save_joint(js):
            seconds["joint"] = joint_before + time.perf_counter() - t3
            save(phase="joint", joint=js)

        q, prior = _joint_roughness(prob, q, torch.cat([p[2] for p in parts]), grid_shape,
                                    state.get("joint") if state["phase"] == "joint" else None,
                                    save_joint if checkpoint is not None else None, tick=lambda: bar.update(1))
        sums = []
        parts = _final(prob, q, sums)
        rd, rs, prior["albedo_cg_iterations"] = _joint_albedos(prob, sums, torch.cat([p[2] for p in parts]),
                                                               torch.cat([p[3] for p in parts]), grid_shape,
                                                               prior["joint_sigma2"])
        sizes = [len(p[2]) for p in parts]
        parts = [(g, loss, a, b) for (g, loss, _, _), a, b in zip(parts, rd.split(sizes), rs.split(sizes))]
    seconds["joint"] = joint_before + time.perf_counter() - t3
    bar.update(bar.total - bar.n)  # the trials and iterations a converged fit did not need
    bar.close()
    geom = {k: torch.cat([p[0][k] for p in parts]) for k in parts[0][0]}
    info = {"init_seconds": seconds["init"], "seconds_per_iteration": seconds["iterations"] / max(c.steps, 1),
            "propagation_seconds": seconds["propagation"], "propagation_restarts": restarted,
            "joint_seconds": seconds["joint"], **prior, "texel_q": texel_q,
            "texel_loss": torch.cat([p[1] for p in parts]).cpu().numpy()}
    return _result(prob, geom, torch.cat([p[2] for p in parts]), torch.cat([p[3] for p in parts]),
                   history / max(prob.n if refitted is None else refitted, 1), t_start, info)


def _resumed(checkpoint, prob: _Problem) -> dict | None:
    """The state a killed fit saved to `checkpoint` (_fit_direct), checked against this problem, or None."""
    state = checkpoint.load() if checkpoint is not None else None
    if state is None:
        return None
    q, hist = np.asarray(state.get("q")), np.asarray(state.get("history"))
    if (state.get("phase") not in ("chunks", "propagation", "joint") or q.shape != (prob.n, GEOMETRY_SIZE)
            or hist.shape != (prob.config.steps,) or not np.isfinite(q).all()
            or (state["phase"] == "joint" and np.shape(state.get("joint", {}).get("x")) != q.shape)
            or ("changed" in state and np.shape(state["changed"]) != (prob.n,))):
        raise ValueError("the fit's checkpoint does not belong to this fit (another texel count or iteration count, "
                         "or non-finite numbers); remove it to start the fit again")
    return state


def _final(prob: _Problem, q: torch.Tensor, sums: list | None = None) -> list:
    """Per chunk of texels: (geometry, loss, rho_d, rho_s) of the numbers q with their closed-form albedos;
    with a list `sums`, each chunk's albedo sums (model._albedo_sums) are appended to it."""
    parts = []
    with torch.no_grad():
        for idx in _chunks(prob, prob.config.batch):
            geom = _log_geometry(q[idx], prob.frame)
            parts.append((geom, *_projected_loss(prob.part(idx), geom, sums)))
    return parts

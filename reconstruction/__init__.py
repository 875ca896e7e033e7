"""Reconstruction: from a capture folder (the photos, the patterns the LEDs showed, the rig folder it carries) to
OpenSVBRDF maps and latents, the same code for a capture from the twin or from the real device; and the scores of a
reconstruction against the twin's ground truth. It reads the twin through `twin` and never imports `calibration`
(the import contract in pyproject.toml).

    pipeline.py    `hemicube reconstruct`: alignment, extraction, decode, fine-tuning, fitting, into one folder
    output.py      the reconstruction folder's files and the stage folder a killed run resumes from
    stages/        the pipeline's steps (alignment and its check, extraction, latents, fine-tuning, GGX fitting)
    network/       the acquisition network (learned patterns, encoder, decoder): training, the shipped networks
    evaluation/    scores against the truth (maps, renders, novel views and lights) and the report
    many.py        `hemicube reconstruct-many`: every capture folder under one, a Ray task each (twin.batch)
    bench/         the reconstruction's benchmarks (`hemicube bench ...`)
    cli.py         the sub-commands' options and printing
    pretrained/    the shipped networks' files, one folder a rig

Exported here (`__all__`, each loaded on first use: `import reconstruction` imports neither Warp nor torch):
    reconstruct, ReconstructConfig           the pipeline on a capture folder
    evaluate, map_errors                     a reconstruction, or its maps, against the truth
    validation_set, novel_view_scores        two sets of maps under views and lights no capture used
    load_pretrained                          the network shipped for a built-in rig
docs/architecture.md has the picture; docs/accuracy.md the scores and their thresholds."""
from __future__ import annotations

from twin.lazy import lazy_exports as _lazy_exports

# each exported name and the module that defines it, loaded on first use
_LAZY = {"reconstruct": "reconstruction.pipeline", "ReconstructConfig": "reconstruction.pipeline",
         "evaluate": "reconstruction.evaluation.validation", "map_errors": "reconstruction.evaluation.metrics",
         "validation_set": "reconstruction.evaluation.novel_views",
         "novel_view_scores": "reconstruction.evaluation.novel_views",
         "load_pretrained": "reconstruction.network.shipped"}
__all__ = list(_LAZY)
__getattr__, __dir__ = _lazy_exports(__name__, _LAZY)

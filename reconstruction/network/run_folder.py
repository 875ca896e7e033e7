"""A training run's folder (`hemicube train -o RUN`): the names it is known by, without the trainer's imports (torch),
for the commands that check a folder against it before any work (twin.outputs)."""
from __future__ import annotations

from twin.outputs import Kind

CHECKPOINT_JSON = "checkpoint.json"
# a run folder, resumed (twin.outputs): its checkpoint, or the held-out log a run writes before its first one
RUN_FOLDER = Kind("a training run folder", (CHECKPOINT_JSON, "metrics.jsonl"))

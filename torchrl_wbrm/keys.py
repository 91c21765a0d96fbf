"""Names shared across the package's floors: the TensorDict entries the project adds to torchrl's (``"observation"``,
``"action"``, ``("next", ...)`` and the rest keep torchrl's own names) and the file names a run directory holds."""
from __future__ import annotations

__all__ = ["CHECKPOINT", "DENSITY_RATIO", "EPISODE", "HISTORY", "PRIORITY_WEIGHT", "RESULTS"]

#: A transition's density-ratio weight ŵ(x, a) ≈ dP^e/dP^b (stage 1's output, stored over D, read by every weighted
#: loss).
DENSITY_RATIO = "density_ratio"
#: torchrl's per-sample weight of a loss (a prioritized replay buffer's importance weight), multiplied by ŵ.
PRIORITY_WEIGHT = "priority_weight"
#: The id of the episode a transition belongs to (D's episodes are split, weighted and selected by it).
EPISODE = "episode"

#: The trainer's checkpoint in a run directory (models, optimisers, RNG states, step, history), written atomically.
CHECKPOINT = "checkpoint.pt"
#: A finished (or diverged) run's record in its run directory: its config, final figures, flags and status.
RESULTS = "results.json"
#: A run's evaluations during training, one entry per evaluation.
HISTORY = "history.json"

"""Names shared across the package's floors: the TensorDict entries the project adds to torchrl's (``"observation"``,
``"action"``, ``("next", ...)`` and the rest keep torchrl's own names) and the file names a run directory holds."""
from __future__ import annotations

__all__ = ["BEHAVIOUR", "CHECKPOINT", "DENSITY_RATIO", "DENSITY_RATIO_ESS", "EPISODE", "EXPERT", "EXPERT_LIKE",
           "HELD_OUT_LOSS", "HISTORY", "LOSS_DENSITY_RATIO", "METADATA", "PRIORITY_WEIGHT", "RESULTS", "WEIGHT_ESS"]

#: A transition's density-ratio weight ŵ(x, a) ≈ dP^e/dP^b (stage 1's output, stored over D, read by every weighted
#: loss).
DENSITY_RATIO = "density_ratio"
#: torchrl's per-sample weight of a loss (a prioritized replay buffer's importance weight), multiplied by ŵ.
PRIORITY_WEIGHT = "priority_weight"
#: The id of the episode a transition belongs to (D's episodes are split, weighted and selected by it).
EPISODE = "episode"
#: D's rows that stage 1 calls the expert's (a boolean mark, :func:`~torchrl_wbrm.ratio.expert_like_episodes`).
EXPERT_LIKE = "expert_like"
#: The two sides of stage 1's paired batch: samples of the behaviour distribution (S^b) and of the expert's (S^e).
BEHAVIOUR = "behaviour"
EXPERT = "expert"

#: Stage 1's loss, its held-out value, and the Kish effective sample sizes the losses report of their weights.
LOSS_DENSITY_RATIO = "loss_density_ratio"
HELD_OUT_LOSS = "held_out_loss"
DENSITY_RATIO_ESS = "density_ratio_ess"
WEIGHT_ESS = "weight_ess"

#: The trainer's checkpoint in a run directory (models, optimisers, RNG states, step, history), written atomically.
CHECKPOINT = "checkpoint.pt"
#: A finished (or diverged) run's record in its run directory: its config, final figures, flags and status.
RESULTS = "results.json"
#: A run's evaluations during training, one entry per evaluation.
HISTORY = "history.json"
#: A saved dataset's record of its files (paths, dtypes, shapes, sizes, checksums) and its provenance.
METADATA = "metadata.json"

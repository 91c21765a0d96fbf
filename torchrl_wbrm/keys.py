"""Names shared across the package's floors: the file names a run directory holds."""
from __future__ import annotations

__all__ = ["CHECKPOINT"]

#: The trainer's checkpoint in a run directory (models, optimisers, RNG states, step, history), written atomically.
CHECKPOINT = "checkpoint.pt"

"""Where a module keeps its tensors, for the floors that move a module or a rollout to it."""
from __future__ import annotations

import torch

__all__ = ["device_of"]


def device_of(module) -> torch.device | None:
    """The device of ``module``'s first parameter, else of its first buffer; ``None`` for a module (or a plain
    callable) with neither."""
    for tensors in ("parameters", "buffers"):
        for tensor in getattr(module, tensors, lambda: ())():
            return tensor.device
    return None

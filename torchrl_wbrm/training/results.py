"""Writing a run's files: strict JSON, atomic replacement, and the kill tests' hook.

* :func:`json_safe` — NaN and ±inf become ``null``, so ``results.json`` stays valid JSON.
* :func:`atomic_write`, :func:`create_fresh`, :func:`pause_for_test` — the package's one writer of whole files and
  the kill tests' hook (``torchrl_wbrm._files``, below every floor that writes), re-exported here.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from torchrl_wbrm._files import TEST_PAUSE_ENV, WriteFailed, atomic_write, create_fresh, pause_for_test

__all__ = ["TEST_PAUSE_ENV", "WriteFailed", "atomic_write", "create_fresh", "json_safe", "pause_for_test", "write_json"]


def json_safe(obj):
    """``obj`` with NaN and ±inf replaced by ``None`` (valid JSON), tensors and numpy scalars as numbers."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, torch.Tensor) and obj.numel() == 1:
        obj = obj.item()
    if hasattr(obj, "item") and callable(obj.item) and not isinstance(obj, (str, bytes)):
        try:
            obj = obj.item()
        except (TypeError, ValueError):
            pass
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_json(path: Path, obj) -> None:
    """Write ``obj`` as strict JSON (``allow_nan=False`` after :func:`json_safe`), atomically (:func:`atomic_write`)."""
    text = json.dumps(json_safe(obj), indent=2, default=float, allow_nan=False)
    atomic_write(path, lambda f: f.write(text.encode()))

"""Kept for imports written before stage 1 became public: :func:`shape_weights` lives in
:mod:`torchrl_wbrm.ratio.weights`."""
from torchrl_wbrm.ratio.weights import shape_weights

__all__ = ["shape_weights"]

"""The package's docstring examples run (``doctest``), module by module."""
from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest
import torch

import torchrl_wbrm

MODULES = sorted(
    info.name for info in pkgutil.walk_packages(torchrl_wbrm.__path__, prefix="torchrl_wbrm.")
)
FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def _has_examples(name: str) -> bool:
    finder = doctest.DocTestFinder(exclude_empty=True)
    return any(test.examples for test in finder.find(importlib.import_module(name)))


@pytest.mark.parametrize("name", [m for m in MODULES if _has_examples(m)])
def test_docstring_examples(name):
    torch.set_num_threads(1)
    state = torch.get_rng_state()
    try:
        result = doctest.testmod(importlib.import_module(name), optionflags=FLAGS, report=True, verbose=False)
    finally:
        torch.set_rng_state(state)
    assert result.failed == 0, f"{result.failed} of {result.attempted} docstring examples of {name} failed"


def test_the_examples_are_collected():
    names = [m for m in MODULES if _has_examples(m)]
    assert {"torchrl_wbrm.objectives.weighted_bellman", "torchrl_wbrm.ratio.fitting"} <= set(names), names

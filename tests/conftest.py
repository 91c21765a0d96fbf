"""Shared pytest fixtures."""
from __future__ import annotations

import os

import pytest
import torch

#: The test files that take the longest, slowest first, each with the sum of its entries among the 70 slowest of one
#: ``pytest -q -n 2 --dist loadfile --durations=70`` run here (2 cores, 3 December 2026). The README's test command passes
#: ``--no-loadscope-reorder``, so pytest-xdist hands files out in collection order, and this order makes that the
#: longest-first rule: while one worker runs test_baselines.py, the other takes the next ones. xdist's own order
#: (files with the most tests first) left the few-test, minute-long subprocess files for last, one worker running
#: them while the other idled. A file not listed keeps its place after these; a stale list costs balance only.
SLOWEST_FILES = (
    "test_benchmark_learning.py",  # about 4 min under load (each benchmark task at two budgets); idle: to measure
    "test_baselines.py",  # 193 s: every algo's learning tests and the recipe for every algo
    "test_recipes.py",  # 105 s
    "test_studies_quick.py",  # 195 s under load (paper_tables --quick runs every registered algorithm: 129 s)
    "test_first_hour.py",  # 90 s under load (the README commands as a user types them)
    "test_examples.py",  # 56 s
    "test_launchers.py",  # 44 s
    "test_minari.py",  # 43 s
)


def pytest_configure(config):
    """Under pytest-xdist (``-n 2``) every worker, and every subprocess it starts, runs torch on one thread.

    Two workers on two cores with torch's default of one thread per core each oversubscribe the machine; measured
    here, oversubscribed OpenMP threads slowed small ops up to 100x.
    """
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ["OMP_NUM_THREADS"] = "1"
        torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    """The files of ``SLOWEST_FILES`` first, slowest first; every other test keeps its order after them."""
    rank = {name: i for i, name in enumerate(SLOWEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the order within a file is kept


@pytest.fixture
def single_thread():
    """Run a small-network training test on one intra-op thread.

    Tiny networks gain nothing from a second thread, and when another process shares the 2-core machine, OpenMP's
    spinning threads made the LQ learning test 6x slower (58 s on two threads against 9.5 s on one).
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)

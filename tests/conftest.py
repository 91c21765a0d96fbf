"""Shared pytest fixtures."""
from __future__ import annotations

import os
from collections import Counter

import pytest
import torch

from tests.forked import mark_pandas_absent

mark_pandas_absent()


def pytest_configure(config):
    """Under pytest-xdist (``-n 2``) every worker, and every subprocess it starts, runs torch on one thread.

    Two workers on two cores with torch's default of one thread per core each oversubscribe the machine; measured
    here, oversubscribed OpenMP threads slowed small ops up to 100x.
    """
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ["OMP_NUM_THREADS"] = "1"
        torch.set_num_threads(1)


def pytest_sessionfinish(session):
    """Stop the fork server of :mod:`tests.forked`, if a test started one, and wait for it (its runs' CPU time then
    counts with the worker's)."""
    from tests import forked

    forked.stop()


def pytest_collection_modifyitems(config, items):
    """Files holding ``slow``-marked tests first, the most slow tests first; every other file keeps its place after.

    The README's test command passes ``--no-loadscope-reorder``, so pytest-xdist hands whole files (``--dist
    loadfile``) to its workers in this order: the long files start first, one per worker, and the many short ones fill
    in behind them, instead of a minute-long file starting last while the other worker idles. A test that takes more
    than a few seconds is marked ``slow`` where it is written; nothing here names a file.
    """
    slow = Counter(item.path for item in items if item.get_closest_marker("slow") is not None)
    first = {}
    for index, item in enumerate(items):
        first.setdefault(item.path, index)
    items.sort(key=lambda item: (-slow[item.path], first[item.path]))  # stable: the order within a file is kept


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

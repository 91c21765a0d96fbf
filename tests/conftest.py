"""Shared pytest fixtures."""
from __future__ import annotations

import os

import pytest
import torch


def pytest_configure(config):
    """Under pytest-xdist (``-n 2``) every worker, and every subprocess it starts, runs torch on one thread.

    Two workers on two cores with torch's default of one thread per core each oversubscribe the machine; measured
    here, oversubscribed OpenMP threads slowed small ops up to 100x.
    """
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ["OMP_NUM_THREADS"] = "1"
        torch.set_num_threads(1)


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

"""Shared pytest fixtures."""
from __future__ import annotations

import pytest
import torch


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

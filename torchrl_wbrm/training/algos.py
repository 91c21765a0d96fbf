"""The algorithms, as the trainer and earlier scripts import them: a re-export of :mod:`torchrl_wbrm.algos`
(one file per algorithm there; this module defines nothing of its own)."""
from __future__ import annotations

from torchrl_wbrm.algos import (
    ALGOS,
    Algo,
    AlgoContext,
    AlgoSpec,
    adam_options,
    algo_names,
    build_algo,
    get_algo,
    register_algo,
)
from torchrl_wbrm.algos.base import descend as _descend  # noqa: F401  (benchmarks/bench_update.py)
from torchrl_wbrm.algos.bc import build_bc
from torchrl_wbrm.algos.brm import build_brm
from torchrl_wbrm.algos.cql import build_cql
from torchrl_wbrm.algos.ddpg import build_ddpg
from torchrl_wbrm.algos.dqn import build_dqn
from torchrl_wbrm.algos.fqi import build_fqi
from torchrl_wbrm.algos.iql import build_iql
from torchrl_wbrm.algos.mabo import build_mabo
from torchrl_wbrm.algos.td3bc import build_td3bc
from torchrl_wbrm.algos.wbrm import build_wbrm
from torchrl_wbrm.modules import ActionGrid, make_tanh_normal_actor  # re-exported here (they lived here before)
from torchrl_wbrm.objectives._fast import ForeachSoftUpdate  # noqa: F401  (benchmarks/bench_update.py)

__all__ = [
    "ALGOS",
    "ActionGrid",
    "Algo",
    "AlgoContext",
    "AlgoSpec",
    "adam_options",
    "algo_names",
    "build_algo",
    "build_bc",
    "build_brm",
    "build_cql",
    "build_ddpg",
    "build_dqn",
    "build_fqi",
    "build_iql",
    "build_mabo",
    "build_td3bc",
    "build_wbrm",
    "get_algo",
    "make_tanh_normal_actor",
    "register_algo",
]

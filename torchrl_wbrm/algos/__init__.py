"""Every method the trainer runs, one file per algorithm, each a configuration of the trainer's one loop.

A file ``torchrl_wbrm/algos/<name>.py`` holds the algorithm's settings (a dataclass: ``baselines.<name>`` in the
schema and the Hydra node ``algo/<name>``) and its builder, registered with :func:`register_algo`::

    @dataclass
    class MyConfig:
        alpha: float = 1.0

    def _check(settings: MyConfig, key: str) -> None:
        if not settings.alpha > 0:
            raise ValueError(f"{key}.alpha must be > 0, got {settings.alpha!r}.")

    @register_algo("mine", config=MyConfig, validate=_check, loss="...", reference="...")
    def build_mine(ctx: AlgoContext) -> Algo:
        ...

Every module of this package whose name does not start with ``_`` (other than ``base`` and ``registry``) is imported
here, so adding an algorithm is adding its file: ``algo=mine`` is then a valid choice of the recipe, its settings are
``baselines.mine.*`` and it appears in ``recipes/paper_tables.py``'s algorithms and in :func:`algo_table`.

``build_algo(name, context)`` returns an :class:`Algo`. The trainer samples a batch from the algo's buffer (D, or
S^e for behaviour cloning), calls ``algo.step(batch, step)`` inside its one loop and evaluates ``algo.policy`` (under
``set_exploration_type(DETERMINISTIC)``: a stochastic actor acts by its mode) and, where the method has a
``Q(x, a)`` network, ``algo.q_value`` against the exact Q*. No algorithm has a loop of its own.

Every method gets the same data, the same network widths (``q.num_cells``, ``q.actor_num_cells``), the same
optimiser (Adam, ``q.lr`` for critics, ``q.actor_lr`` for actors), batch size, step budget, γ, target rate
``q.target_tau`` and the same output bias of Q (mean(r) / (1 − γ), ``q.init_bias``). Their own settings are under
``baselines.<name>``.
"""
from __future__ import annotations

import importlib
import pkgutil

from torchrl_wbrm.algos.base import Algo, AlgoContext, adam_options
from torchrl_wbrm.algos.registry import (
    ALGOS,
    AlgoSpec,
    algo_names,
    algo_table,
    get_algo,
    register_algo,
    store_algo_configs,
    unregister_algo,
)

__all__ = [
    "ALGOS",
    "Algo",
    "AlgoContext",
    "AlgoSpec",
    "adam_options",
    "algo_names",
    "algo_table",
    "build_algo",
    "get_algo",
    "register_algo",
    "store_algo_configs",
    "unregister_algo",
]

#: the package's modules that are not algorithms
_NOT_ALGOS = ("base", "registry")


def _import_algorithms() -> None:
    found = [m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_") and m.name not in _NOT_ALGOS]
    for name in sorted(found):  # registration order: by file name
        importlib.import_module(f"{__name__}.{name}")


def build_algo(name: str, ctx: AlgoContext) -> Algo:
    """The :class:`Algo` registered as ``name`` (``ValueError`` naming an unknown name and the known ones)."""
    return get_algo(name)(ctx)


_import_algorithms()

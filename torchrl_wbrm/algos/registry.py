"""The registry of algorithms: one :class:`AlgoSpec` per name, filled by :func:`register_algo`.

Every consumer reads it rather than a list of its own: the recipe's ``algo`` choices
(:func:`~torchrl_wbrm.training.config.validate_config`), the ``baselines.<name>`` settings of the schema
(:class:`~torchrl_wbrm.training.config.BaselinesConfig`), the Hydra ``algo`` group (:func:`store_algo_configs`),
the plots' titles, ``recipes/paper_tables.py``'s algorithms and the README's table (:func:`algo_table`, checked by a
test).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable

__all__ = ["ALGOS", "AlgoSpec", "algo_names", "algo_table", "get_algo", "register_algo", "store_algo_configs",
           "unregister_algo"]


@dataclass(frozen=True)
class AlgoSpec:
    """One registered algorithm.

    Attributes:
        name: the ``algo=<name>`` of the recipe.
        build: ``build(context) -> Algo`` (:class:`~torchrl_wbrm.algos.AlgoContext`, :class:`~torchrl_wbrm.algos.Algo`).
        config: its settings' dataclass (``baselines.<name>`` in the schema, stored in the Hydra ``algo`` group's node
            ``algo/<name>``), or ``None`` when it has none of its own.
        validate: ``validate(settings, key)`` checks the values a type cannot (``key`` is ``"baselines.<name>"``, for
            the message); raises ``ValueError`` naming the setting.
        fits_ratio: stage 1 (the density ratio ŵ) runs before it when ``ratio.source=learned``: ``True``, or a
            function of the run's config saying whether it does (``bc`` fits ŵ only to weight what it clones,
            ``baselines.bc.data=weighted``); :meth:`fits_ratio_for` reads either.
        bellman_residual: it fits a Bellman residual (its algo's ``bellman_loss``), so ``q.select`` can score its
            evaluations on the held-out D episodes; the task's defaults of
            :attr:`~torchrl_wbrm.tasks.Task.BELLMAN_RESIDUAL_SETTINGS` (Q's LayerNorm, ``q.select``) apply to
            it, and the shared ones to the others (:func:`~torchrl_wbrm.training.config.resolve_defaults`).
        critic_layer_norm: the task's default of Q's LayerNorm (``q.layer_norm``) applies to it although it fits no
            Bellman residual (``q.select`` stays the shared one): an algo whose reference has nothing that keeps its
            critic on the data, so that its Q, left without the LayerNorm, grows without bound on a task's data
            (DDPG).
        loss, reference: one line each (Markdown) for the docs' table.
        loss_title: the title of the training-loss panel of ``training_curve.png``.
        clones_expert: its actor has the cloning term of S^e's actions (``q.expert_bc_alpha``), which
            ``q.expert_bc_weighted_d`` and ``q.expert_bc_from_d`` extend; for any other algo those settings are
            refused (:func:`~torchrl_wbrm.training.config.validate_config`).
    """

    name: str
    build: Callable
    config: type | None = None
    validate: Callable[[Any, str], None] | None = None
    fits_ratio: bool | Callable[[Any], bool] = False
    bellman_residual: bool = False
    critic_layer_norm: bool = False
    loss: str = ""
    reference: str = ""
    loss_title: str = ""
    clones_expert: bool = False

    def __call__(self, context):
        return self.build(context)

    def fits_ratio_for(self, cfg) -> bool:
        """Whether stage 1 runs before this algo with the run's config ``cfg`` (:attr:`fits_ratio`)."""
        return bool(self.fits_ratio(cfg) if callable(self.fits_ratio) else self.fits_ratio)


#: name -> :class:`AlgoSpec`, in registration order (``ALGOS[name](context)`` builds the algo).
ALGOS: dict[str, AlgoSpec] = {}


def register_algo(name: str, *, config: type | None = None, validate=None, fits_ratio=False,
                  bellman_residual: bool = False, critic_layer_norm: bool = False, loss: str = "",
                  reference: str = "", loss_title: str = "", clones_expert: bool = False) -> Callable:
    """Decorator: register ``build(context) -> Algo`` under ``name`` (returns the builder unchanged).

    ``config`` must be a dataclass (its defaults are the ``algo/<name>`` node's); a name registered twice is an error.
    """
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"register_algo: the name must be an identifier (it is a config key), got {name!r}.")
    if config is not None and not dataclasses.is_dataclass(config):
        raise TypeError(f"register_algo({name!r}): config must be a dataclass, got {config!r}.")

    def decorator(build: Callable) -> Callable:
        if name in ALGOS:
            raise ValueError(f"register_algo: the algo {name!r} is registered already ({ALGOS[name].build.__module__}).")
        ALGOS[name] = AlgoSpec(name, build, config, validate, fits_ratio, bellman_residual, critic_layer_norm,
                               loss, reference, loss_title or f"{name}: training losses", clones_expert=clones_expert)
        return build

    return decorator


def unregister_algo(name: str) -> None:
    """Remove ``name`` from the registry (for tests that register a toy algorithm)."""
    get_algo(name)
    del ALGOS[name]


def algo_names() -> list[str]:
    """The registered names, in registration order."""
    return list(ALGOS)


def get_algo(name: str) -> AlgoSpec:
    """The :class:`AlgoSpec` registered as ``name``; ``ValueError`` naming the unknown name and the known ones."""
    try:
        return ALGOS[name]
    except (KeyError, TypeError):
        raise ValueError(f"algo={name!r} is not known: choose one of {sorted(ALGOS)}.") from None


def store_algo_configs(config_store, settings: type | None = None) -> None:
    """Store every algo's node in the Hydra ``algo`` group (``algo=<name>``), package ``_global_``: it sets ``algo``
    and, where the algo has settings, ``baselines.<name>`` to its dataclass's defaults (it comes after the env's
    defaults in the recipe's defaults list, so an algo's settings win over them; the command line still wins).

    ``settings``: the schema's ``BaselinesConfig``; an algo whose settings it lacks (registered after the schema was
    built, i.e. after :mod:`torchrl_wbrm.training.config` was imported) is an error naming it.
    """
    fields = None if settings is None else {f.name for f in dataclasses.fields(settings)}
    for spec in ALGOS.values():
        node: dict = {"algo": spec.name}
        if spec.config is not None:
            if fields is not None and spec.name not in fields:
                raise ValueError(
                    f"algo {spec.name!r} was registered after torchrl_wbrm.training.config built the schema, so its "
                    f"settings baselines.{spec.name} are not in it: make it a file of torchrl_wbrm/algos/ (imported "
                    f"with the package), or import it before torchrl_wbrm.training.config."
                )
            node["baselines"] = {spec.name: spec.config}
        config_store.store(group="algo", name=spec.name, node=node, package="_global_")


def algo_table() -> str:
    """The registered algorithms as a Markdown table (name, loss, reference), as the README shows it."""
    lines = ["| algo | loss | reference |", "|---|---|---|"]
    lines += [f"| `{s.name}` | {s.loss} | {s.reference} |" for s in ALGOS.values()]
    return "\n".join(lines)

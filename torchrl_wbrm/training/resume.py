"""What a resume may change, and whether a run may start: a resumed config may differ from the checkpoint's only in
:data:`CONTINUABLE_KEYS` (``q.steps`` only upwards), a finished run's results are reused only for its own config, and
a run's Hydra record names only the recipe's settings.
"""
from __future__ import annotations

import functools
from dataclasses import fields
from pathlib import Path

from omegaconf import OmegaConf

from torchrl_wbrm.keys import CHECKPOINT
from torchrl_wbrm.training.checkpoint import read_checkpoint
from torchrl_wbrm.training.config import WBRMConfig, config_as_dict, config_schema
from torchrl_wbrm.training.rundir import RunDirClaim, check_run_dir, claim_run_dir

__all__ = ["CONTINUABLE_KEYS", "CONTINUABLE_PREFIXES", "REUSABLE_KEYS", "REUSABLE_PREFIXES", "changed_keys",
           "check_finished_config", "check_resume_config", "check_run_record", "check_run_request", "is_continuable"]


#: Keys a resumed run may change: they do not change what has been trained (``q.steps`` only upwards).
CONTINUABLE_KEYS = (
    "q.steps",
    "q.eval_every",
    "checkpoint_every",
    "resume",
    "overwrite",
    "plots",
    "threads",
    "data_cache",
)


#: Whole sections a resumed run may change: evaluation and logging settings.
CONTINUABLE_PREFIXES = ("eval.", "logger.")


def check_run_record(record: Path, overrides: list[str]) -> None:
    """Refuse a run's Hydra record (``.hydra/overrides.yaml``, re-applied by ``resume=``) holding an override that is
    not a setting of the recipe's own config (:class:`~torchrl_wbrm.training.config.WBRMConfig`): a record Hydra wrote
    holds only those (``env=lqr_exp3``, ``q.lr=0.003``; Hydra's own settings go to ``hydra.yaml``). Anything else,
    such as a ``hydra.callbacks`` entry whose ``_target_`` Hydra would import and call, is refused before Hydra sees
    it: a resume never runs what a file in the run directory names."""
    settings = {f.name for f in fields(WBRMConfig)}
    for override in overrides:
        key = override.split("=", 1)[0].lstrip("+~")
        if "=" not in override or key.split(".", 1)[0].split("/", 1)[0] not in settings:
            raise ValueError(
                f"Cannot resume: {record} holds the override {override!r}, which is not a setting of this recipe "
                f"(a run's record holds only its own settings, such as env=lqr_exp3 or q.lr=0.003); nothing in it was "
                f"applied."
            )


def _flatten(node, prefix: str = "") -> dict:
    if isinstance(node, dict):
        out = {}
        for k, v in node.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: node}


@functools.lru_cache(maxsize=1)
def _setting_defaults() -> dict:
    """Every setting's default value, flattened to dotted keys (the schema's own values: null where an env's task
    resolves it)."""
    return _flatten(OmegaConf.to_container(config_schema()))


def changed_keys(old: dict, new: dict) -> dict[str, tuple]:
    """Dotted key -> ``(old, new)`` for every leaf that differs between two nested config dicts.

    A setting the old config lacks and the new one holds at its default is no change: the old config was saved
    before the setting existed, and a setting is added with the behaviour it had before as its default."""
    a, b = _flatten(old), _flatten(new)
    missing = object()
    defaults = _setting_defaults()
    out = {}
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key, missing), b.get(key, missing)
        if va is missing and key in defaults and vb == defaults[key]:
            continue
        if va != vb:
            out[key] = (None if va is missing else va, None if vb is missing else vb)
    return out


def is_continuable(key: str) -> bool:
    return key in CONTINUABLE_KEYS or key.startswith(CONTINUABLE_PREFIXES)


#: Keys a finished run's results may be reused under when they differ: the continuable ones that change no figure a
#: finished run reports (not the step budget, the evaluation schedule or the evaluation settings).
REUSABLE_KEYS = tuple(k for k in CONTINUABLE_KEYS if not k.startswith("q."))


REUSABLE_PREFIXES = ("logger.",)


def _describe(changes: dict[str, tuple]) -> str:
    return "; ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in changes.items())


def check_finished_config(path: Path, saved: dict, now: dict) -> None:
    """Refuse to reuse a finished run's results (``path``) for a config that differs from the one it ran with, outside
    :data:`REUSABLE_KEYS` (the logger, plots, threads and where the data are cached): every such key is named with its
    old and new value. A study that skips its finished runs would otherwise report them as this config's."""
    refused = {k: v for k, v in changed_keys(saved, now).items()
               if k not in REUSABLE_KEYS and not k.startswith(REUSABLE_PREFIXES)}
    if refused:
        raise ValueError(
            f"{path} holds a finished run with other settings: {_describe(refused)}. Its results are not this config's; write "
            f"this config's runs to another directory (a study's --out), or delete that run to redo it."
        )


def check_resume_config(path: Path, saved: dict, now: dict, state: dict) -> dict[str, tuple]:
    """Refuse a resume whose config differs from the checkpoint's outside :data:`CONTINUABLE_KEYS` (every such key
    named with its old and new value), or whose ``q.steps`` is below the steps already trained. Returns the
    (continuable) changes."""
    changes = changed_keys(saved, now)
    refused = {k: v for k, v in changes.items() if not is_continuable(k)}
    if "q.steps" in changes and now.get("q", {}).get("lr_schedule", "constant") != "constant":
        refused["q.steps"] = changes["q.steps"]  # the schedule's horizon is the step budget
    if refused:
        raise ValueError(
            f"Cannot resume from {path}: these settings differ from the checkpoint's and cannot change in a resumed "
            f"run: {_describe(refused)}. Only {', '.join(CONTINUABLE_KEYS)} (q.steps upwards, and not with an lr schedule) and "
            f"the {', '.join(p.rstrip('.') for p in CONTINUABLE_PREFIXES)} settings may change; start a new run for "
            f"anything else."
        )
    trained = state.get("step", 0) if state.get("stage") in ("q", "done") else 0
    steps = now.get("q", {}).get("steps")
    if steps is not None and steps < trained:
        raise ValueError(
            f"Cannot resume from {path}: q.steps={steps} is smaller than the {trained} steps already trained "
            f"(a resumed run can only continue; start a new run for a smaller budget)."
        )
    return changes


def check_run_request(cfg, run_dir: Path, *, resume: bool, claim: RunDirClaim | None = None,
                      task=None) -> tuple[RunDirClaim, dict | None]:
    """Everything that can refuse a run in ``run_dir`` before it starts, with nothing written: the directory is
    claimed (:func:`claim_run_dir`, unless ``claim`` is this run's already), then a resume's checkpoint is read and
    its config compared (:func:`check_resume_config`), or a new run's directory checked for an earlier run
    (:func:`check_run_dir`, nothing removed yet). Returns the claim (released again if the run is refused) and the
    checkpoint read (``None`` for a new run)."""
    run_dir = Path(run_dir)
    path = run_dir / CHECKPOINT
    if resume and not path.is_file():
        read_checkpoint(path)  # FileNotFoundError naming the directory; nothing is created
    claim = claim or claim_run_dir(run_dir)
    sd = None
    try:
        if resume:
            sd = read_checkpoint(path)
            check_resume_config(path, dict(sd["config"]), config_as_dict(cfg, task), sd["state"])
        else:
            check_run_dir(run_dir, overwrite=cfg.overwrite, remove=False)
    except BaseException:
        claim.release()
        raise
    return claim, sd

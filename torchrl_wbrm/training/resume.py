"""What a resume may change, and whether a run may start: a resumed config may differ from the checkpoint's only in
:data:`CONTINUABLE_KEYS` (``q.steps`` only upwards), a finished run's results are reused only for its own config, and
a run's Hydra record names only the recipe's settings.
"""
from __future__ import annotations

import functools
from pathlib import Path

from omegaconf import OmegaConf

from torchrl_wbrm.keys import CHECKPOINT, RESULTS
from torchrl_wbrm.training.checkpoint import read_checkpoint
from torchrl_wbrm.training.config import config_as_dict, config_schema
from torchrl_wbrm.training.validation import check_writable_folder
from torchrl_wbrm.training.rundir import (RunDirClaim, check_run_dir, claim_run_dir, given_claim, holds_run,
                                          refuse_links)

__all__ = ["CONFIG_GROUPS", "CONTINUABLE_KEYS", "CONTINUABLE_PREFIXES", "REUSABLE_KEYS", "REUSABLE_PREFIXES",
           "changed_keys", "check_finished_config", "check_resume_config", "check_run_record", "check_run_request",
           "check_seeds_resume", "group_options", "is_continuable", "read_run_record"]


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


#: The recipe's config groups: ``<group>=<option>`` picks one of the files shipped under ``configs/<group>/`` (for
#: ``algo``, one of the registered algos). A run's record may name only those (:func:`group_options`).
CONFIG_GROUPS = ("env", "algo", "logger")


def group_options(group: str) -> tuple[str, ...]:
    """The options of the recipe's config group ``group`` (:data:`CONFIG_GROUPS`): the YAML files shipped in
    ``configs/<group>/``, or for ``algo`` the registered algos."""
    if group == "algo":
        from torchrl_wbrm.algos import ALGOS

        return tuple(ALGOS)
    from torchrl_wbrm.configs import CONFIG_DIR

    return tuple(sorted(path.stem for path in (CONFIG_DIR / group).glob("*.yaml")))


def _refuse_record(record: Path, override: str, why: str) -> ValueError:
    return ValueError(
        f"Cannot resume: {record} holds the override {override!r}, which {why}; a run's record holds only the "
        f"recipe's own settings with values it offers (such as env=lqr_exp3 or q.lr=0.003), so nothing in it was "
        f"applied."
    )


def check_run_record(record: Path, overrides: list[str]) -> None:
    """Refuse a run's Hydra record (``.hydra/overrides.yaml``, re-applied by ``resume=``) holding anything but the
    recipe's own settings with values the recipe offers: each entry must be ``key=value`` (``++key=value`` too) for a
    setting of :class:`~torchrl_wbrm.training.config.WBRMConfig`, with a plain value (no sweep, no ``${...}``
    interpolation), and a group override (``env=``, ``algo=``, ``logger=``) must name one of the group's shipped
    options (:func:`group_options`), never a path: Hydra would load a YAML file a path names, honour its
    ``# @package _global_`` and instantiate its ``hydra.callbacks``. Everything is refused before Hydra sees it: a
    resume never runs nor loads what a file in the run directory names."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import OverrideType
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    schema = config_schema()
    missing = object()
    for override in overrides:
        if not isinstance(override, str):
            raise _refuse_record(record, override, "is not a 'key=value' string")
        try:
            (parsed,) = parser.parse_overrides([override])
        except (HydraException, ValueError) as err:
            raise _refuse_record(record, override, f"is not an override Hydra can read ({str(err).splitlines()[0]})") \
                from None
        key = parsed.key_or_group
        group = key in CONFIG_GROUPS
        if not group and ("/" in key or OmegaConf.select(schema, key, default=missing) is missing):
            raise _refuse_record(record, override, "is not a setting of this recipe")
        if parsed.type not in (OverrideType.CHANGE, OverrideType.FORCE_ADD):
            raise _refuse_record(record, override, "adds or deletes a key instead of setting one")
        if parsed.package is not None:
            raise _refuse_record(record, override, "places a config at another package ('@')")
        if parsed.is_sweep_override():
            raise _refuse_record(record, override, "is a sweep, not one value")
        value = parsed.value()
        if group:
            options = group_options(key)
            if not isinstance(value, str) or value not in options:
                raise _refuse_record(record, override, f"is not one of the {key} group's options "
                                                       f"({', '.join(options)})")
            continue
        if "${" in str(value):
            raise _refuse_record(record, override, "holds an interpolation ('${...}'), not a plain value")


def read_run_record(record: Path) -> list[str]:
    """The overrides of a run's Hydra record (``.hydra/overrides.yaml``), read as data (YAML's safe loader: a list
    of strings) and checked (:func:`check_run_record`). A record that is not UTF-8, not YAML or not a list of
    strings is a one-line ``ValueError`` naming the file."""
    import yaml

    record = Path(record)
    try:
        text = record.read_bytes().decode("utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(f"Cannot resume: {record} is not UTF-8 text (byte {err.start}), so it is not the run's "
                         f"record of its overrides; nothing in it was applied.") from None
    except OSError as err:
        raise ValueError(f"Cannot resume: {record} cannot be read ({err.strerror}).") from None
    try:
        saved = yaml.safe_load(text)
    except yaml.YAMLError as err:
        where = getattr(err, "problem_mark", None)
        at = f" at line {where.line + 1}" if where is not None else ""
        raise ValueError(f"Cannot resume: {record} is not valid YAML{at}, so it is not the run's record of its "
                         f"overrides; nothing in it was applied.") from None
    saved = [] if saved is None else saved
    if not isinstance(saved, list) or not all(isinstance(o, str) for o in saved):
        raise ValueError(f"Cannot resume: {record} is not a list of overrides (strings such as 'q.lr=0.003'); nothing "
                         f"in it was applied.")
    check_run_record(record, saved)
    return saved


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


def check_seeds_resume(cfg, run_dir: Path, task=None) -> None:
    """Before a multi-seed run is resumed, each of its seeds' folders: a finished seed's results must be this
    config's (:func:`check_finished_config`), and a seed's checkpoint one this config may continue
    (:func:`check_resume_config`); a damaged file is named. Nothing is written."""
    import json

    now = config_as_dict(cfg, task)
    now.pop("seeds", None)
    for seed in cfg.seeds:
        seed_dir = Path(run_dir) / f"seed{seed}"
        now_seed = {**now, "seed": int(seed)}
        done = seed_dir / RESULTS
        if done.is_file():
            try:
                results = json.loads(done.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError) as err:
                raise ValueError(f"Cannot resume: {done} is damaged ({err}); delete it to run seed {seed} again.") \
                    from None
            if not (isinstance(results, dict) and isinstance(results.get("config"), dict)):
                raise ValueError(f"Cannot resume: {done} holds no config (key 'config'), so it cannot be told to be "
                                 f"this run's seed {seed}; delete it to run that seed again.")
            check_finished_config(done, results["config"], now_seed)
        elif (seed_dir / CHECKPOINT).is_file():
            sd = read_checkpoint(seed_dir / CHECKPOINT)
            check_resume_config(seed_dir / CHECKPOINT, dict(sd["config"]), now_seed, sd["state"])


def check_run_request(cfg, run_dir: Path, *, resume: bool, claim: RunDirClaim | None = None,
                      task=None) -> tuple[RunDirClaim, dict | None]:
    """Everything that can refuse a run in ``run_dir`` before it starts, with nothing written: the directory is
    claimed (:func:`claim_run_dir`, unless ``claim`` is this run's already), then a resume's checkpoint is read and
    its config compared (:func:`check_resume_config`), or a new run's directory checked for an earlier run
    (:func:`check_run_dir`, nothing removed yet); a directory where something the run writes into is a symbolic
    link is refused (:func:`~torchrl_wbrm.training.rundir.refuse_links`). Returns the claim (released again if the run is refused) and the
    checkpoint read (``None`` for a new run). A given ``claim`` must be of ``run_dir``
    (:func:`~torchrl_wbrm.training.rundir.given_claim`)."""
    run_dir = Path(run_dir)
    claim = given_claim(claim, run_dir)
    path = run_dir / CHECKPOINT
    seeds = getattr(cfg, "seeds", None)
    if resume and seeds:  # a multi-seed run: its seeds' folders are checked by their own trainers
        if not run_dir.is_dir():
            raise FileNotFoundError(f"Cannot resume: {run_dir} is not a directory (no multi-seed run there).")
        claim = claim or claim_run_dir(run_dir)
        try:
            refuse_links(run_dir)
            check_writable_folder(run_dir, "resume")
            check_seeds_resume(cfg, run_dir, task)
        except BaseException:
            claim.release()
            raise
        return claim, None
    if resume and not path.is_file():
        read_checkpoint(path)  # FileNotFoundError naming the directory; nothing is created
    claim = claim or claim_run_dir(run_dir)
    sd = None
    try:
        if resume or not (cfg.overwrite and holds_run(run_dir)):  # overwrite=true removes the earlier outputs
            refuse_links(run_dir)
        check_writable_folder(run_dir, "resume" if resume else "hydra.run.dir")
        if resume:
            sd = read_checkpoint(path)
            check_resume_config(path, dict(sd["config"]), config_as_dict(cfg, task), sd["state"])
        else:
            check_run_dir(run_dir, overwrite=cfg.overwrite, remove=False)
    except BaseException:
        claim.release()
        raise
    return claim, sd

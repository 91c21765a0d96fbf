"""Loggers through ``torchrl.record.loggers.get_logger`` (CSV by default, wandb offline unless asked otherwise), the
wandb run's final summary, the studies' summary runs, and the console's library logging.

A wandb run of the recipe (``logger=wandb``) holds:

* the resolved config (``wandb.config``);
* the step metrics in sections ``ratio/``, ``q/``, ``weights/`` and ``eval/``; torchrl's ``WandbLogger`` declares
  each with ``define_metric`` against its section's step (``ratio/step``, ``q/step``, ``eval/step``), and
  ``eval/step`` is the training step of stage 2, so evaluation curves plot against it;
* in the run summary, the final figures with their 95% CIs (``final/return``, ``final/return_ci``, ...), the
  datasets' sizes and mean returns (``data/...``) and the status;
* the run's plots as images (``plots/training_curve``, ``plots/evaluation``) and the final results as a
  ``wandb.Table`` (``results``: one row per figure, with its CI);
* a readable name (``wbrm · lqr_exp1 · seed 0``), ``group`` (``logger.group``, else the Hydra sweep's folder
  name), ``job_type`` = the algorithm and tags env, algo and seed.

Read an offline run back with ``wandb leet <run dir>/wandb`` (a terminal dashboard) or
``wandb leet inspect --summary --json <run dir>/wandb/latest-run``; upload it with ``wandb sync <run dir>/wandb/offline-run-*``.
"""
from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Iterable

from torchrl.record.loggers import get_logger

from torchrl_wbrm.keys import DENSITY_RATIO_ESS, LOSS_DENSITY_RATIO, WEIGHT_ESS
from torchrl_wbrm._console import quiet_libraries

__all__ = ["make_logger", "configure_console", "finish_logger", "progress_postfix", "run_name", "log_scalars",
           "log_run_summary", "log_study_summary", "markdown_tables", "truncate_csv_logs"]

def configure_console(verbose: bool) -> None:
    """Silence the libraries' INFO chatter on the console (``verbose=False``), or bring it back (``True``): torchrl's
    storage lines and the like (:func:`torchrl_wbrm._console.quiet_libraries`, also applied on import) and wandb's
    own output."""
    quiet_libraries(bool(verbose))
    os.environ["WANDB_SILENT"] = "false" if verbose else "true"


#: The training figures a progress bar shows, in order of preference, with their short labels.
PROGRESS_FIGURES = {
    LOSS_DENSITY_RATIO: "loss", DENSITY_RATIO_ESS: "ess",  # stage 1
    "loss_value": "loss", "loss_bc": "loss", "loss_qvalue": "loss_q", "loss_actor": "actor", "q_mean": "Q",
    WEIGHT_ESS: "ess", "loss_cql": "cql", "entropy": "H",
}
#: The most characters a progress bar's figures take: a 120-column line keeps them whole beside the bar and counts.
PROGRESS_WIDTH = 44


def progress_postfix(figures: dict[str, float], width: int = PROGRESS_WIDTH) -> str:
    """The few figures a tqdm bar shows (``loss=0.0231 actor=-99.1 Q=84.2``): the known ones first, by short
    label, then others, up to ``width`` characters, so the line is never cut.

        >>> progress_postfix({"loss_value": 0.023123, "q_mean": 84.2312, "loss_actor": -99.12, "weight_ess": 1640.2})
        'loss=0.0231 actor=-99.1 Q=84.2 ess=1.64e+03'
    """
    known = [(PROGRESS_FIGURES[k], v) for k, v in sorted(figures.items(), key=lambda kv: _order(kv[0]))
             if k in PROGRESS_FIGURES]
    others = [(k, v) for k, v in figures.items() if k not in PROGRESS_FIGURES]
    parts: list[str] = []
    for label, value in [*known, *others]:
        part = f"{label}={float(value):.3g}"
        if len(" ".join([*parts, part])) > width:
            break
        parts.append(part)
    return " ".join(parts)


def _order(key: str) -> int:
    return list(PROGRESS_FIGURES).index(key) if key in PROGRESS_FIGURES else len(PROGRESS_FIGURES)


def run_name(config: dict) -> str:
    """``"<algo> · <env> · seed <seed>"`` from a resolved recipe config."""
    return f"{config.get('algo', 'wbrm')} · {config.get('env', {}).get('name', '?')} · seed {config.get('seed', '?')}"


def _hydra_sweep_group() -> str | None:
    """The Hydra sweep folder's name in a multirun (its runs share a wandb group), else ``None``."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hc = HydraConfig.get()
        if hc.mode == RunMode.MULTIRUN:
            return Path(hc.sweep.dir).name
    except (ImportError, ValueError, AttributeError):
        pass
    return None


def _wandb_settings():
    import wandb

    return wandb.Settings(console="off", silent=True, x_disable_stats=True, x_disable_machine_info=True)


def make_logger(logger_cfg, run_dir: str | os.PathLike, experiment_name: str, config: dict | None = None):
    """A torchrl ``Logger`` writing under ``run_dir`` (``None`` when ``logger_cfg.backend`` is empty).

    wandb runs ``offline`` unless ``logger_cfg.mode`` says ``"online"`` (this project assumes no network and no API
    key). With a recipe ``config`` (the resolved one, recorded as the run's config) the wandb run gets a readable
    name, a group, ``job_type`` = the algorithm and tags env / algo / seed (see the module's docstring).
    """
    backend = logger_cfg.backend
    run_dir = Path(run_dir)
    if backend == "":
        return None
    if backend == "csv":
        logger = get_logger("csv", logger_name=str(run_dir / "logs"), experiment_name=experiment_name)
        if config is not None:
            logger.log_hparams(config)
        return logger
    if backend != "wandb":
        raise ValueError(f"logger.backend must be 'csv', 'wandb' or '' (none), got {backend!r}.")
    config = dict(config or {})
    _wandb_dirs_under(run_dir)
    if not os.environ.get("WANDB_SILENT"):
        os.environ["WANDB_SILENT"] = "true"
    kwargs = {"project": logger_cfg.project, "config": config, "settings": _wandb_settings()}
    if config:
        env_name, algo = config.get("env", {}).get("name", "env"), str(config.get("algo", "wbrm"))
        group = getattr(logger_cfg, "group", None) or _hydra_sweep_group()
        kwargs.update(job_type=algo, tags=[str(env_name), algo, f"seed{config.get('seed', 0)}"])
        if group:
            kwargs["group"] = str(group)
        experiment_name = run_name(config)
    if logger_cfg.mode == "offline":
        kwargs["offline"] = True
    else:
        kwargs["mode"] = logger_cfg.mode
    kwargs["log_env_packages"] = False  # the run's config is the recipe's, not the list of installed packages
    return get_logger("wandb", logger_name=str(run_dir), experiment_name=experiment_name, wandb_kwargs=kwargs)


#: wandb's folders outside its run directory (``$HOME``'s by default): its data folder (artifact staging copies of the
#: images and tables a run logs) and its cache. A run puts them under ``<run dir>/wandb/``; a value the user set is
#: kept.
_WANDB_DIRS = {"WANDB_DATA_DIR": ".data", "WANDB_CACHE_DIR": ".cache"}
_WANDB_DIRS_SET: dict[str, str] = {}


def _wandb_dirs_under(run_dir: Path) -> None:
    """Point wandb's data (staging) and cache folders into ``run_dir/wandb/`` (its debug logs go to its run folder
    there already), unless the user set them: a run writes nothing under ``$HOME``."""
    for var, name in _WANDB_DIRS.items():
        if os.environ.get(var) not in (None, _WANDB_DIRS_SET.get(var)):
            continue  # the user's own setting
        path = str(Path(run_dir).absolute() / "wandb" / name)
        os.environ[var] = _WANDB_DIRS_SET[var] = path


def truncate_csv_logs(logs: Path, stage: str, step: int, *, stages=("ratio", "q"),
                      reevaluated: bool = False) -> list[Path]:
    """Drop the rows of a resumed run's CSV logs (``logs/<experiment>/scalars/<section>/<name>.csv``, torchrl's
    ``CSVLogger``) that the run writes again after its checkpoint (stage ``stage``, step ``step``): so each step is
    logged once, even after a SIGKILL between two checkpoints.

    Sections: ``ratio/`` and ``ratio_eval/`` are stage 1's, ``q/`` and ``eval/`` stage 2's (by its step), and
    ``weights/`` is written once when stage 2 starts. A checkpoint in stage 1 keeps stage 1's rows up to ``step``
    and none of stage 2's; one in stage 2 keeps stage 1's and ``weights/`` and stage 2's rows up to ``step``; a
    finished run (``"done"``) keeps every row, but with ``reevaluated`` (a finished run evaluated anew) its
    evaluation rows at ``step`` go. Each file is rewritten whole (created fresh, then renamed). Returns the files
    changed."""
    from torchrl_wbrm.training.results import atomic_write

    logs = Path(logs)
    changed = []
    if not logs.is_dir() or logs.is_symlink():
        return changed
    order = {name: i for i, name in enumerate(stages)}
    for path in sorted(logs.glob("*/scalars/*/*.csv")):
        section = path.parent.name
        owner = {"ratio": "ratio", "ratio_eval": "ratio", "weights": "weights", "q": "q", "eval": "q"}.get(section)
        if owner is None:
            continue
        if stage == "done":
            limit = step - 1 if reevaluated and section == "eval" else None
        elif owner == "weights":
            limit = None if order.get(stage, 0) > 0 else -1
        elif owner == stage:
            limit = step
        else:  # another stage: before this one (all kept) or after it (none kept)
            limit = None if order.get(owner, 0) < order.get(stage, 0) else -1
        if limit is None:
            continue
        lines = path.read_text().splitlines(keepends=True)
        kept = [line for line in lines if _csv_step(line) is not None and _csv_step(line) <= limit]
        if len(kept) != len(lines):
            atomic_write(path, lambda f, text="".join(kept): f.write(text.encode()))
            changed.append(path)
    return changed


def _csv_step(line: str) -> int | None:
    try:
        return int(float(line.split(",", 1)[0]))
    except ValueError:
        return None


def _wandb_run(logger):
    """The live ``wandb`` run behind a torchrl ``WandbLogger`` (``None`` for any other logger)."""
    from torchrl.record.loggers.wandb import WandbLogger

    return logger.experiment if isinstance(logger, WandbLogger) else None


def finish_logger(logger) -> None:
    """End the wandb run behind ``logger`` (marked finished, its files flushed) when the run is over, rather than
    at the process's exit; any other logger: nothing to do."""
    run = _wandb_run(logger) if logger is not None else None
    if run is not None:
        run.finish()


def _flat_numbers(record: dict, prefix: str = "") -> dict[str, float]:
    out = {}
    for key, value in record.items():
        if isinstance(value, dict):
            out.update(_flat_numbers(value, f"{prefix}{key}/"))
        elif isinstance(value, bool):
            continue
        elif isinstance(value, (int, float)):
            out[f"{prefix}{key}"] = value
    return out


def log_scalars(logger, scalars: dict[str, float], step: int) -> None:
    """Log each finite figure of ``scalars`` at ``step`` (``logger``: a torchrl ``Logger``, or ``None``: nothing)."""
    if logger is not None:
        for k, v in scalars.items():
            if v is not None and math.isfinite(v):
                logger.log_scalar(k, v, step=step)


def log_run_summary(logger, results: dict, run_dir: str | os.PathLike) -> None:
    """Put a finished run's final figures (with CIs), its plots and a results table into its wandb run.

    Summary keys: ``final/<figure>`` and ``final/<figure>_ci`` (every float of the final evaluation), ``data/...``
    (set sizes, mean returns of the datasets), ``weights/...``, ``status``. Media: ``plots/<name>`` for every PNG
    in ``run_dir``. Table ``results``: columns ``figure, value, ci95, stderr``. A no-op for other loggers.
    """
    import wandb

    run = _wandb_run(logger)
    if run is None:
        return
    final = results.get("final", {}) or {}
    summary = {f"final/{k}": v for k, v in _flat_numbers(final).items() if k != "step"}
    summary.update({f"data/{k}": v for k, v in _flat_numbers(results.get("data", {}) or {}).items()})
    summary.update({f"weights/{k}": v for k, v in _flat_numbers(results.get("weights", {}) or {}).items()})
    summary["status"] = results.get("status", "finished")
    for key, value in summary.items():
        run.summary[key] = value
    rows = []
    for key, value in final.items():
        if key == "step" or key.endswith(("_ci", "_stderr")) or not isinstance(value, (int, float)):
            continue
        rows.append([key, float(value), final.get(f"{key}_ci"), final.get(f"{key}_stderr")])
    media = {"results": wandb.Table(columns=["figure", "value", "ci95", "stderr"], data=rows)}
    for png in sorted(Path(run_dir).glob("*.png")):
        media[f"plots/{png.stem}"] = wandb.Image(str(png))
    run.log(media)


#: the longest table name :func:`markdown_tables` makes from a heading (wandb names a logged table's artifact
#: ``run-<id>-<key>`` and refuses names over 128 characters)
MAX_TABLE_NAME = 60


def markdown_tables(text: str) -> dict[str, tuple[list[str], list[list[str]]]]:
    """The pipe tables of a Markdown text, named by the heading above each (``"table_<i>"`` if none; lower case,
    runs of other characters as ``_``, at most :data:`MAX_TABLE_NAME` characters):
    ``{name: (columns, rows)}``."""
    tables: dict[str, tuple[list[str], list[list[str]]]] = {}
    heading, lines = None, text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        if line.startswith("#"):
            heading = line.lstrip("#").strip()
        if line.startswith("|") and i + 1 < len(lines) and re.fullmatch(r"\|[\s:|-]+\|", lines[i + 1].strip()):
            columns = [c.strip() for c in line.strip("|").split("|")]
            rows = []
            i += 2
            while i < len(lines) and lines[i].strip().startswith("|"):
                cells = [c.strip() for c in lines[i].strip().strip("|").split("|")]
                rows.append((cells + [""] * len(columns))[: len(columns)])
                i += 1
            base = re.sub(r"[^A-Za-z0-9_]+", "_", heading or f"table_{len(tables)}").strip("_").lower() or "table"
            base = base[:MAX_TABLE_NAME].rstrip("_")  # wandb refuses artifact names over 128 characters
            name, n = base, 1
            while name in tables:
                n += 1
                name = f"{base}_{n}"
            tables[name] = (columns, rows)
            continue
        i += 1
    return tables


def log_study_summary(study: str, out_dir: str | os.PathLike, *, tables: Iterable[str | os.PathLike] = (),
                      figures: Iterable[str | os.PathLike] = (), project: str = "torchrl_wbrm",
                      mode: str | None = None) -> str | None:
    """Log a study's tables (Markdown files, each pipe table a ``wandb.Table``) and figures (images) to the
    summary run of its group (``group=study``, ``job_type="summary"``), written under ``out_dir/wandb``.

    Offline unless ``mode`` (or ``WANDB_MODE``) says ``"online"``; ``WANDB_MODE=disabled`` skips it. Returns the
    run's folder (``None`` when skipped). Never fails the study: a wandb error is reported in one line.
    """
    mode = mode or os.environ.get("WANDB_MODE") or "offline"
    if mode == "disabled":
        return None
    try:
        import wandb

        os.environ.setdefault("WANDB_SILENT", "true")
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        run = wandb.init(project=project, group=study, job_type="summary", name=f"{study} · summary",
                         tags=[study, "summary"], dir=str(out_dir), mode="online" if mode == "online" else "offline",
                         config={"study": study, "out": str(out_dir)}, settings=_wandb_settings(), reinit="create_new")
        media = {}
        for path in tables:
            path = Path(path)
            if not path.is_file():
                continue
            for name, (columns, rows) in markdown_tables(path.read_text()).items():
                media[f"tables/{path.stem}/{name}"] = wandb.Table(columns=columns, data=rows)
        for path in figures:
            path = Path(path)
            if path.is_file():
                media[f"figures/{path.stem}"] = wandb.Image(str(path))
        if media:
            run.log(media)
        run.summary["tables"] = sorted(k for k in media if k.startswith("tables/"))
        run.summary["figures"] = sorted(k for k in media if k.startswith("figures/"))
        run_dir = run.dir
        run.finish()
        return str(Path(run_dir).parent)
    except Exception as err:  # noqa: BLE001 (the study's own outputs are written; the dashboard is extra)
        print(f"wandb summary run of {study} not written: {err}")
        return None

"""The offline value estimate and the checkpoint-selection criteria against the online returns of every evaluated
checkpoint of recipe runs: LQR exp1–3 (the recipe's defaults) and the benchmark's four Minari tasks (the
3-demonstration cell, the Minari defaults).

    python -m torchrl_wbrm.data.benchmark --data-path datasets/benchmark          # the Minari datasets
    python recipes/offline_value_validation.py run --data-path datasets/benchmark --out results/ope_validation
    python recipes/offline_value_validation.py report --out results/ope_validation   # the tables

``run`` trains each (cell, seed) with :class:`~torchrl_wbrm.training.WBRMTrainer` evaluation by evaluation
(``run(until=step)``) and, at each evaluated checkpoint, estimates the current policy's value from D alone with
:func:`~torchrl_wbrm.training.offline_value.offline_value_figures` (FQE, and ŵ-weighted FQE where stage 2 weighted
D; under a forked random state, so training draws what it draws without them). The last step's parameters are
valued as trained, also where ``q.select`` delivers an earlier evaluation's (read back from the checkpoint's
``"q_last"``). One JSON line per (cell, seed) goes to ``<out>/checkpoints.jsonl``; a finished (cell, seed) is
skipped when the command is run again.

``report`` computes, per cell, over seeds (mean and 95% t-interval over seeds):

- against the online return of every checkpoint (the evaluation's own episodes: ``eval.train_episodes``, the final
  one ``eval.episodes``): the absolute and relative error of the estimate, Spearman's rank correlation over a run's
  checkpoints, and regret@1 (the best checkpoint's online return minus that of the checkpoint the estimate ranks
  first), as DOPE and SCOPE-RL report them;
- regret@1 of each selection criterion: the lowest held-out Bellman residual, the lowest ŵ-weighted one, the highest
  FQE estimate (uniform and ŵ-weighted) and the last step; none of them runs an episode.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # a clone's recipes run without installing

LQR_CELLS = ("lqr_exp1", "lqr_exp2", "lqr_exp3")
MINARI_TASKS = ("pendulum", "mountain_car", "lunar_lander", "inverted_pendulum")
CRITERIA = {  # name -> (figure, +1: the highest is chosen, -1: the lowest)
    "held-out residual": ("held_out_bellman_residual", -1),
    "held-out ŵ-weighted residual": ("held_out_weighted_residual", -1),
    "FQE estimate": ("offline_value", +1),
    "ŵ-weighted FQE estimate": ("offline_value_weighted", +1),
    "last step": ("step", +1),
}


def cell_overrides(cell: str, data_path: Path | None) -> list[str]:
    """The recipe's overrides of one cell: an LQR system at its defaults, or a Minari task's 3-demonstration cell."""
    if cell in LQR_CELLS:  # every criterion's figure recorded; the parameters trained are q.select's alike
        return [f"env={cell}", "q.select=held_out_weighted_residual"]
    if data_path is None:
        raise ValueError(f"cell {cell!r} reads the benchmark's Minari datasets: give --data-path.")
    return ["env=minari", f"env.minari.data_path={data_path}",
            f"env.minari.expert=benchmark/{cell}/expert-pool-v0", "env.minari.expert_episodes=3",
            f"env.minari.behaviour=benchmark/{cell}/behaviour-expert10-v0"]


def compose(overrides: list[str]):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from torchrl_wbrm.configs import CONFIG_DIR
    from torchrl_wbrm.training.config import register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return hydra_compose("wbrm_offline", overrides=[*overrides, "threads=1", "logger=none", "plots=false"])


def _value(trainer, steps: int) -> dict:
    """The trainer's own offline value of its current actor (:meth:`WBRMTrainer.offline_value`, forked RNG)."""
    figures, _ = trainer.offline_value(steps)
    return {k: figures[k] for k in ("offline_value", "offline_value_weighted") if k in figures}


_KEPT = ("return", "return_ci", "normalised_score", "held_out_bellman_residual", "held_out_weighted_residual")


def run_one(cell: str, seed: int, *, data_path: Path | None, out: Path, fqe_steps: int,
            overrides: list[str] = ()) -> dict:
    """Train one (cell, seed) evaluation by evaluation; the checkpoints' online figures, residuals and estimates."""
    from torchrl_wbrm.training import WBRMTrainer
    from torchrl_wbrm.training.checkpoint import read_checkpoint

    start = time.time()
    run_dir = out / "runs" / f"{cell}_seed{seed}"
    cfg = compose([*cell_overrides(cell, data_path), *overrides, f"seed={seed}", "overwrite=true"])
    trainer = WBRMTrainer(cfg, run_dir, logger=None, progress=False)
    steps, every = trainer.cfg.q.steps, trainer.cfg.q.eval_every
    rows = []
    for step in range(every, steps, every):
        trainer.run(until=step)
        record = [r for r in trainer.history if r["stage"] == "q" and r["step"] == step][-1]
        rows.append({"step": step, **{k: record[k] for k in _KEPT if k in record}, **_value(trainer, fqe_steps)})
    trainer.run()
    final = [r for r in trainer.history if r["stage"] == "q"][-1]
    delivered = final.get("selected_step", steps)
    last = {"step": steps}
    if delivered == steps:
        last.update({k: final[k] for k in _KEPT if k in final})
        last.update(_value(trainer, fqe_steps))
    else:  # the delivered parameters are an earlier evaluation's: value the last step's as trained
        last.update({k: v for k, v in [r for r in trainer.history if r["stage"] == "q_last"][-1].items() if k in _KEPT})
        delivered_state = trainer.q_loss.state_dict()
        trainer.q_loss.load_state_dict(read_checkpoint(run_dir / "checkpoint.pt")["q_last"])
        last.update(_value(trainer, fqe_steps))
        trainer.q_loss.load_state_dict(delivered_state)
    rows.append(last)
    trainer.release()
    return {"cell": cell, "seed": seed, "select": trainer.cfg.q.select, "delivered_step": delivered,
            "delivered_return": final.get("return"), "checkpoints": rows, "fqe_steps": fqe_steps,
            "seconds": round(time.time() - start, 1)}


def done_runs(path: Path) -> dict:
    if not path.is_file():
        return {}
    out = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.strip():
            rec = json.loads(line)
            out[(rec["cell"], rec["seed"])] = rec
    return out


# ---------------------------------------------------------------------------------------------------- reporting
def spearman(x: list[float], y: list[float]) -> float:
    """Spearman's rank correlation (average ranks for ties); NaN where either side is constant (every checkpoint at
    the same return: no ranking to recover)."""
    from scipy.stats import spearmanr

    if len(set(x)) < 2 or len(set(y)) < 2:
        return float("nan")

    return float(spearmanr(x, y).statistic)


def chosen(rows: list[dict], figure: str, sign: int) -> dict | None:
    """The checkpoint a criterion picks: the highest ``sign * figure`` (the earliest wins a tie); ``None`` where no
    checkpoint has the figure."""
    have = [r for r in rows if r.get(figure) is not None]
    return max(have, key=lambda r: (sign * r[figure], -r["step"])) if have else None


def delivered_row(rec: dict) -> dict:
    """The checkpoint row of the parameters the cell's default delivers: LQR's is the last step's (``q.select=last``;
    the study's LQR runs select only to record every criterion's figure), a Minari task's the run's own choice."""
    step = rec["checkpoints"][-1]["step"] if rec["cell"] in LQR_CELLS else rec["delivered_step"]
    return [r for r in rec["checkpoints"] if r["step"] == step][-1]


def run_figures(rec: dict) -> dict:
    """One run's validation figures (see the module docstring)."""
    rows = rec["checkpoints"]
    online = [r["return"] for r in rows]
    best = max(online)
    out = {}
    for key in ("offline_value", "offline_value_weighted"):
        if all(r.get(key) is not None for r in rows):
            errors = [abs(r[key] - r["return"]) for r in rows]
            out[f"{key}:abs_error"] = sum(errors) / len(errors)
            out[f"{key}:rel_error"] = 100 * sum(e / max(abs(r["return"]), 1e-12) for e, r in zip(errors, rows)) / len(rows)
            out[f"{key}:spearman"] = spearman([r[key] for r in rows], online)
            last = rows[-1]
            out[f"{key}:last_error"] = last[key] - last["return"]
    for name, (figure, sign) in CRITERIA.items():
        pick = chosen(rows, figure, sign)
        if pick is not None:
            out[f"regret:{name}"] = best - pick["return"]
    return out


def report(records: list[dict]) -> str:
    from torchrl_wbrm.evaluation.stats import mean_ci

    def cell_text(values: list[float], digits: int = 2) -> str:
        values = [v for v in values if v == v]
        if not values:
            return "–"
        ci = mean_ci(values)
        half = (ci.high - ci.low) / 2
        return f"{ci.mean:.{digits}f} ± {half:.{digits}f}" if len(values) > 1 else f"{ci.mean:.{digits}f}"

    cells = list(dict.fromkeys(r["cell"] for r in records))
    figures = {c: [run_figures(r) for r in records if r["cell"] == c] for c in cells}
    seeds = {c: sorted(r["seed"] for r in records if r["cell"] == c) for c in cells}
    lines = ["### The estimate against every checkpoint's online return", "",
             "| cell | seeds | checkpoints | mean online return | FQE: abs. error | FQE: rel. error (%) | FQE: Spearman | "
             "ŵ-FQE: abs. error | ŵ-FQE: rel. error (%) | ŵ-FQE: Spearman |", "|---" * 10 + "|"]
    for c in cells:
        digits = 3 if c in LQR_CELLS else 1
        recs = [r for r in records if r["cell"] == c]
        n_ckpt = len(recs[0]["checkpoints"])
        mean_online = cell_text([sum(x["return"] for x in r["checkpoints"]) / n_ckpt for r in recs], digits)
        row = [c, f"{len(seeds[c])}", f"{n_ckpt}", mean_online]
        for key in ("offline_value", "offline_value_weighted"):
            row += [cell_text([f.get(f"{key}:abs_error", float("nan")) for f in figures[c]], digits),
                    cell_text([f.get(f"{key}:rel_error", float("nan")) for f in figures[c]], 1),
                    cell_text([f.get(f"{key}:spearman", float("nan")) for f in figures[c]], 2)]
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "### The delivered policy's estimate against its online return", "",
              "| cell | delivered by | online return | FQE estimate | FQE: error (%) | ŵ-FQE estimate | "
              "ŵ-FQE: error (%) |", "|---" * 7 + "|"]
    for c in cells:
        digits = 3 if c in LQR_CELLS else 1
        recs = [r for r in records if r["cell"] == c]
        online = [r["delivered_return"] if delivered_row(r)["step"] == r["delivered_step"] else delivered_row(r)["return"]
                  for r in recs]  # the final evaluation (eval.episodes) where it scored these parameters
        row = [c, "last" if c in LQR_CELLS else recs[0]["select"], cell_text(online, digits)]
        for key in ("offline_value", "offline_value_weighted"):
            estimates = [delivered_row(r).get(key, float("nan")) for r in recs]
            row += [cell_text(estimates, digits),
                    cell_text([100 * (e - o) / abs(o) for e, o in zip(estimates, online)], 2)]
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "### Regret@1 of each selection criterion (online return; 0 is the best checkpoint)", "",
              "| cell | best checkpoint's return | " + " | ".join(CRITERIA) + " |", "|---" * (2 + len(CRITERIA)) + "|"]
    for c in cells:
        digits = 3 if c in LQR_CELLS else 1
        recs = [r for r in records if r["cell"] == c]
        best = cell_text([max(x["return"] for x in r["checkpoints"]) for r in recs], digits)
        row = [c, best] + [cell_text([f.get(f"regret:{n}", float("nan")) for f in figures[c]], digits)
                           for n in CRITERIA]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=("run", "report"))
    parser.add_argument("--out", type=Path, default=Path("results/ope_validation"))
    parser.add_argument("--data-path", type=Path, default=None, help="the benchmark's Minari datasets")
    parser.add_argument("--cells", nargs="+", default=[*LQR_CELLS, *MINARI_TASKS])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--fqe-steps", type=int, default=2000, help="Adam steps of each FQE fit")
    parser.add_argument("--overrides", nargs="*", default=[], help="recipe settings for every cell (a smoke test's)")
    from studies.docs_fragments import add_docs_dir_argument, docs_dir_from_args, publish_study, seeds_text

    add_docs_dir_argument(parser)
    args = parser.parse_args(argv)
    records_path = args.out / "checkpoints.jsonl"
    if args.mode == "run":
        torch.set_num_threads(1)
        args.out.mkdir(parents=True, exist_ok=True)
        finished = done_runs(records_path)
        for cell in args.cells:
            for seed in args.seeds:
                if (cell, seed) in finished:
                    continue
                rec = run_one(cell, seed, data_path=args.data_path, out=args.out, fqe_steps=args.fqe_steps,
                              overrides=args.overrides)
                with records_path.open("a", encoding="utf-8") as f:
                    f.write(json.dumps(rec) + "\n")
                print(f"{cell} seed {seed}: {rec['seconds']} s, delivered step {rec['delivered_step']}", flush=True)
    records = [r for r in done_runs(records_path).values() if r["cell"] in args.cells]
    if not records:
        raise SystemExit(f"{records_path} holds no finished run of the cells {args.cells}.")
    text = report(records)
    (args.out / "tables.md").write_text(text, encoding="utf-8")
    print(text)
    if args.mode == "report":  # the docs' tables come from the records of every cell, never from a partial run
        by_seeds: dict[tuple, list[str]] = {}
        for c in dict.fromkeys(r["cell"] for r in records):
            by_seeds.setdefault(tuple(sorted(r["seed"] for r in records if r["cell"] == c)), []).append(c)
        seeds = "; ".join(f"{seeds_text(s)}: {', '.join(cells)}" for s, cells in by_seeds.items())
        steps = sorted({r["fqe_steps"] for r in records})
        publish_study("offline_value_validation", args.out / "tables.md", docs_dir_from_args(args.docs_dir),
                      seeds=seeds, budget=f"each cell's recipe defaults; FQE {', '.join(map(str, steps))} Adam steps "
                      "per estimate (batch 256, lr 1e-3, τ 0.05, a 2×64 SiLU Q)")


if __name__ == "__main__":
    main()

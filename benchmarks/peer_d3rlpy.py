"""TD3+BC, CQL, IQL and BC of this project against d3rlpy 2.8.1's on the same data (LQR exp1 or two Minari
datasets), scored alike.

    python benchmarks/peer_d3rlpy.py                       # LQR exp1: 3,000 updates each, seed 0
    python benchmarks/peer_d3rlpy.py --steps 3000 --cql-steps 1000 --algos td3bc,iql,cql
    python benchmarks/peer_d3rlpy.py --env minari --data-path datasets/benchmark \
        --expert benchmark/pendulum/expert-v0 --behaviour benchmark/pendulum/behaviour-expert10-v0 \
        --algos iql --steps 10000 --eval-episodes 30 --seeds 0,1,2
    python benchmarks/peer_d3rlpy.py --env minari ... --expert benchmark/pendulum/expert-pool-v0 --expert-episodes 3 \
        --algos td3bc,iql,bc --seeds 0,1,2,3,4       # the few-demonstration cell, S^e drawn by each seed

What it does, in order (one process at a time, one torch thread each):

1. builds d3rlpy's own virtual environment (``.peer/d3rlpy-venv``, ignored by git: d3rlpy 2.8.1 pins gymnasium
   1.0.0) with ``python -m venv`` and ``pip install torch==2.13.0 d3rlpy==2.8.1``, unless it is there;
2. exports the transitions this project's algo trains on for the env and the seed (:func:`export_data`:
   for ``env=lqr_exp1`` the behaviour and expert episodes less the held-out episodes, 18,000 transitions at seed 0;
   for ``--env minari`` D, the behaviour dataset's episodes that are not S^b, less the held-out episodes; for ``bc``
   the state-actions it clones, S^e, with zero rewards and every row terminal) to ``data.npz``;
3. per algo, trains d3rlpy's algorithm on exactly those transitions in a subprocess of that venv (every transition
   one two-observation episode, so each (x, a, r, x') is d3rlpy's transition as stored; ``MinMaxActionScaler`` on
   the env's action box; ``StandardObservationScaler`` of those transitions where this project standardises the
   observations (``q.normalise_observations``: Minari, not LQR); γ of the env; d3rlpy's defaults otherwise: 2×256
   ReLU networks, batch 256, its learning rates and τ) and saves its greedy policy as TorchScript (d3rlpy's
   ``save_policy``, the scalers included);
4. trains this project's algo on the same data (``algo=<name>``, the recipe's defaults, ``q.steps`` = the budget,
   plus any ``--set KEY=VALUE`` overrides);
5. scores both policies with this project's evaluator of the env and prints the table, with the seconds per 1,000
   updates of each (d3rlpy: its ``fit`` loop; this project: the trainer's update steps, batch sampling included;
   evaluations out). LQR: the paired regret (``LQRTask``'s evaluator: 1,000 paired episodes against the exact
   optimum, the recipe's ``eval.seed``). Minari: the mean return and D4RL's normalised score over the same
   ``eval.episodes`` episodes of the datasets' gymnasium env (``--eval-episodes``, default the recipe's 100).

Everything is written under ``--out`` (default ``results/peer_d3rlpy``); ``summary.json`` holds the table. With several
``--seeds`` the table gives each side's mean over the seeds with a 95% t interval over them. d3rlpy's
run of an (algo, budget, seed) on the same data (by the sha256 of its arrays) is saved and reused on a later call
(``--rerun-peer`` to train it again; seeded, it gives the same policy); this project's side is always trained anew.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VENV = ROOT / ".peer" / "d3rlpy-venv"
PEER_PINS = ["torch==2.13.0", "d3rlpy==2.8.1"]
ALGOS = ("td3bc", "cql", "iql")
LABELS = {"td3bc": "TD3+BC", "cql": "CQL", "iql": "IQL", "bc": "BC"}


def _fragment_name(value: str) -> str:
    """``--publish``: a fragment's name, lower-case letters, digits and ``_`` (it names a file in the docs)."""
    if not value or not all(c.islower() or c.isdigit() or c == "_" for c in value):
        raise argparse.ArgumentTypeError(f"{value!r}: lower-case letters, digits and '_' only (a docs fragment's name)")
    return value


# ---------------------------------------------------------------------- d3rlpy's side (runs in its own venv)
def peer_train(data_path: str, algo: str, steps: int, seed: int, policy_path: str) -> dict:
    """Train d3rlpy's ``algo`` on the exported transitions; save its greedy policy (TorchScript). Runs in the
    d3rlpy venv: imports nothing of this project."""
    import numpy as np
    import torch

    import d3rlpy
    from d3rlpy.dataset import Episode, InfiniteBuffer, ReplayBuffer
    from d3rlpy.preprocessing import MinMaxActionScaler, StandardObservationScaler

    torch.set_num_threads(1)
    data = np.load(data_path)
    obs, act, rew = data["observation"], data["action"], data["reward"].reshape(-1, 1)
    next_obs, terminated = data["next_observation"], data["terminated"].reshape(-1).astype(bool)
    low, high = data["action_low"], data["action_high"]
    episodes = []
    for i in range(obs.shape[0]):  # one transition each: (x, a, r, x'), or (x, a, r, terminal) when terminated
        if terminated[i]:
            episodes.append(Episode(obs[i:i + 1], act[i:i + 1], rew[i:i + 1], True))
        else:
            episodes.append(Episode(np.stack([obs[i], next_obs[i]]), np.stack([act[i], np.zeros_like(act[i])]),
                                    np.stack([rew[i], np.zeros_like(rew[i])]), False))
    dataset = ReplayBuffer(InfiniteBuffer(), episodes=episodes, action_space=d3rlpy.ActionSpace.CONTINUOUS,
                           action_size=act.shape[1])
    assert dataset.transition_count == obs.shape[0], (dataset.transition_count, obs.shape[0])
    d3rlpy.seed(seed)
    scalers = {"action_scaler": MinMaxActionScaler(minimum=low, maximum=high), "gamma": float(data["gamma"])}
    if "observation_scaler" in data.files and bool(data["observation_scaler"]):  # fitted on the transitions
        scalers["observation_scaler"] = StandardObservationScaler()
    config = {
        "td3bc": lambda: d3rlpy.algos.TD3PlusBCConfig(**scalers),
        "cql": lambda: d3rlpy.algos.CQLConfig(**scalers),
        "iql": lambda: d3rlpy.algos.IQLConfig(**scalers),
        "bc": lambda: d3rlpy.algos.BCConfig(**scalers),
    }[algo]()
    learner = config.create(device="cpu:0")
    learner.build_with_dataset(dataset)
    start = time.perf_counter()
    learner.fit(dataset, n_steps=steps, n_steps_per_epoch=steps, show_progress=False, save_interval=10**9,
                logger_adapter=d3rlpy.logging.NoopAdapterFactory())
    seconds = time.perf_counter() - start
    learner.save_policy(policy_path)
    return {"algo": algo, "steps": steps, "seconds": seconds, "config": config.serialize(),
            "d3rlpy": d3rlpy.__version__, "torch": torch.__version__}


# ---------------------------------------------------------------------- this project's side
def _venv_works(python: Path) -> int:
    """0 if ``python`` imports d3rlpy 2.8.1 and torch 2.13.0, else the check's exit code (negative: a signal)."""
    return subprocess.run([str(python), "-c", "import d3rlpy, torch; assert d3rlpy.__version__ == '2.8.1' and "
                                              "torch.__version__.startswith('2.13.0')"],
                          capture_output=True).returncode


def ensure_venv(venv: Path) -> Path:
    """d3rlpy's own venv: used if it imports d3rlpy and torch at the pinned versions, else built. A venv that exists
    but fails that check (a broken install: a truncated ``.so`` makes ``import numpy`` die of SIGBUS, which pip's
    "already satisfied" would not repair) is deleted and rebuilt when it is this script's own (under ``.peer/``), and
    refused otherwise, naming it."""
    python = venv / "bin" / "python"
    if python.is_file():
        code = _venv_works(python)
        if code == 0:
            return python
        if venv.resolve().parent != VENV.parent.resolve():
            raise SystemExit(f"{venv} exists but its python fails `import d3rlpy, torch` at {PEER_PINS} (exit code "
                             f"{code}); fix or delete it, or pass another --venv.")
        print(f"{venv} fails `import d3rlpy, torch` at {PEER_PINS} (exit code {code}): rebuilding it", flush=True)
        shutil.rmtree(venv)
    venv.parent.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    subprocess.run([str(python), "-m", "pip", "install", "-q", *PEER_PINS], check=True)
    code = _venv_works(python)
    if code:
        raise SystemExit(f"{venv} was built but fails `import d3rlpy, torch` at {PEER_PINS} (exit code {code}).")
    return python


def compose(overrides: list[str]):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from torchrl_wbrm.training.config import register_configs
    from torchrl_wbrm.configs import CONFIG_DIR

    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return hydra_compose("wbrm_offline", overrides=[*overrides, "threads=1"])


def env_overrides(args) -> list[str]:
    """The recipe's env overrides of ``--env`` (and, for ``minari``, its datasets and evaluation episodes)."""
    if args.env != "minari":
        return [f"env={args.env}"]
    missing = [name for name in ("data_path", "expert", "behaviour") if not getattr(args, name)]
    if missing:
        raise SystemExit(f"--env minari needs {', '.join('--' + m.replace('_', '-') for m in missing)}.")
    out = ["env=minari", f"env.minari.data_path={Path(args.data_path).resolve()}", f"env.minari.expert={args.expert}",
           f"env.minari.behaviour={args.behaviour}"]
    if args.expert_episodes is not None:
        out.append(f"env.minari.expert_episodes={args.expert_episodes}")
    return out


def base_overrides(seed: int, steps: int, algo: str, env: list[str] | None = None) -> list[str]:
    return [*(env or ["env=lqr_exp1"]), f"seed={seed}", f"algo={algo}", f"q.steps={steps}", f"q.eval_every={steps}",
            "checkpoint_every=0", "plots=false", "logger=none"]


def export_data(trainer, path: Path) -> int:
    """The transitions the trainer's algo trains on, as ``.npz``: D (``q_train_data``), or for an algo that clones
    S^e (``bc``, ``baselines.bc.data=expert``) S^e's state-actions, with zero rewards and every row terminal (cloning
    reads neither)."""
    import numpy as np
    import torch

    spec = trainer.action_spec
    if trainer.algo.data == "expert":
        d = trainer.datasets.expert_samples[:]
        reward, next_observation = torch.zeros(d.shape[0], 1), d["observation"]
        terminated = torch.ones(d.shape[0], 1, dtype=torch.bool)
    else:
        d = trainer.q_train_data
        reward, next_observation, terminated = d["next", "reward"], d["next", "observation"], d["next", "terminated"]
    np.savez(path, observation=d["observation"].numpy(), action=d["action"].numpy(),
             reward=reward.numpy(), next_observation=next_observation.numpy(),
             terminated=terminated.numpy(), action_low=spec.space.low.numpy(),
             action_high=spec.space.high.numpy(), gamma=np.float64(trainer.gamma),
             observation_scaler=np.bool_(bool(trainer.cfg.q.normalise_observations)))
    return d.shape[0]


def data_digest(path: Path) -> str:
    """sha256 of the exported arrays (names, dtypes, shapes, bytes): the same data, whenever it was written."""
    import numpy as np

    digest = hashlib.sha256()
    with np.load(path) as data:
        for name in sorted(data.files):
            array = np.ascontiguousarray(data[name])
            digest.update(f"{name}:{array.dtype}:{array.shape}".encode())
            digest.update(array.tobytes())
    return digest.hexdigest()


def project_run(algo: str, steps: int, seed: int, run_dir: Path, data_path: Path | None,
                overrides: list[str] | None = None, env: list[str] | None = None):
    """Train this project's ``algo`` (the recipe's defaults, then ``overrides``), exporting its training rows to
    ``data_path`` first; returns (trainer, final figures, seconds of the update steps, rows exported or ``None``)."""
    import torch

    from torchrl_wbrm.training import WBRMTrainer

    torch.set_num_threads(1)
    cfg = compose([*base_overrides(seed, steps, algo, env), *(overrides or [])])
    trainer = WBRMTrainer(cfg, run_dir, progress=False)
    exported = export_data(trainer, data_path) if data_path is not None else None
    seconds = [0.0]
    q_step = trainer._q_step

    def timed(step: int) -> dict:
        start = time.perf_counter()
        out = q_step(step)
        seconds[0] += time.perf_counter() - start
        return out

    trainer._q_step = timed
    results = trainer.run()
    return trainer, results["final"], seconds[0], exported


def score(trainer, policy_path: Path) -> dict:
    """The trainer's evaluator's figures (LQR: the paired regret; Minari: the return and normalised score) of a
    TorchScript policy (a batch of observations -> a batch of actions), over the recipe's evaluation episodes."""
    import torch
    from tensordict.nn import TensorDictModule

    scripted = torch.jit.load(str(policy_path))
    dim, action_dim = (trainer.q_train_data[key].shape[-1] for key in ("observation", "action"))

    def act(x: torch.Tensor) -> torch.Tensor:  # one observation or a batch, as the evaluator steps its env
        return scripted(x.float().reshape(-1, dim)).reshape(*x.shape[:-1], action_dim)

    policy = TensorDictModule(act, in_keys=["observation"], out_keys=["action"])
    ec = trainer.cfg.eval
    with torch.no_grad():
        return trainer.evaluation.evaluator.evaluate(policy, episodes=ec.episodes, seed=ec.seed)


def _mean_ci(values: list[float]) -> tuple[float, float]:
    """Mean and the half-width of its 95% t interval over the values (0 for one value)."""
    import numpy as np
    from scipy import stats

    a = np.asarray(values, dtype=float)
    if a.size < 2:
        return float(a.mean()), 0.0
    return float(a.mean()), float(stats.t.ppf(0.975, a.size - 1) * a.std(ddof=1) / np.sqrt(a.size))


def _peer_policy(args, peer_python: Path, out: Path, data_path: Path, algo: str, steps: int, seed: int) -> tuple:
    """d3rlpy's policy for (algo, steps, seed) on the exported data: trained in its venv, or its saved run reused."""
    data_sha = data_digest(data_path)
    policy_path = out / f"d3rlpy_{algo}_{steps}steps_seed{seed}.pt"
    record = policy_path.with_suffix(".json")
    peer = json.loads(record.read_text()) if record.is_file() and policy_path.is_file() else None
    if peer is None or peer.get("data_sha256") != data_sha or args.rerun_peer:
        proc = subprocess.run([str(peer_python), __file__, "--peer-worker", str(data_path), algo, str(steps),
                               str(seed), str(policy_path)], capture_output=True, text=True,
                              env={**os.environ, "OMP_NUM_THREADS": "1"})
        if proc.returncode:
            how = f"killed by signal {-proc.returncode}" if proc.returncode < 0 else f"exit code {proc.returncode}"
            raise SystemExit(f"d3rlpy {algo} failed ({how}, in {peer_python}):\n{proc.stderr[-4000:]}")
        peer = {**json.loads(proc.stdout.strip().splitlines()[-1]), "data_sha256": data_sha}
        record.write_text(json.dumps(peer, indent=1, default=str))
    else:
        print(f"d3rlpy {algo}: its run on the same data, budget and seed is reused ({record})", flush=True)
    return policy_path, peer


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=3000, help="updates per algo, both libraries (default 3000)")
    parser.add_argument("--cql-steps", type=int, default=None, help="CQL's budget, both libraries (default --steps)")
    parser.add_argument("--algos", default=",".join(ALGOS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seeds", default=None, help="comma-separated training seeds (default: --seed)")
    parser.add_argument("--env", default="lqr_exp1", help="lqr_exp1 (default) or minari (with the three below)")
    parser.add_argument("--data-path", default=None, help="minari: the folder the dataset ids are looked up in")
    parser.add_argument("--expert", default=None, help="minari: the expert dataset's id (S^e)")
    parser.add_argument("--behaviour", default=None, help="minari: the behaviour dataset's id (D and S^b)")
    parser.add_argument("--expert-episodes", type=int, default=None,
                        help="minari: env.minari.expert_episodes (default: every expert episode)")
    parser.add_argument("--eval-episodes", type=int, default=None,
                        help="eval.episodes of both policies (default: the recipe's, the env's)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a recipe override for this project's side only (repeatable), e.g. baselines.iql.lr=3e-4")
    parser.add_argument("--no-peer", action="store_true", help="train and score this project's side only")
    parser.add_argument("--out", default=str(ROOT / "results" / "peer_d3rlpy"))
    parser.add_argument("--venv", default=str(VENV))
    parser.add_argument("--rerun-peer", action="store_true",
                        help="train d3rlpy again even where its run on the same data, budget and seed is saved")
    parser.add_argument("--peer-worker", nargs=5, metavar=("DATA", "ALGO", "STEPS", "SEED", "POLICY"),
                        help=argparse.SUPPRESS)
    parser.add_argument("--publish", default=None, metavar="NAME", type=_fragment_name,
                        help="publish the table as the docs fragment results/_generated/NAME.md (a Minari "
                             "comparison's, e.g. locomotion_peer_hopper; without it only LQR exp1's at the defaults is "
                             "published, as peer_d3rlpy)")
    parser.add_argument("--docs-dir", default=None, metavar="PATH",  # the peer worker's venv has no torchrl_wbrm
                        help="the Sphinx docs folder that receives the table (results/_generated/peer_d3rlpy.md); "
                             "default: the clone's docs/; 'none': skip")
    args = parser.parse_args(argv)
    if args.peer_worker:
        data, algo, steps, seed, policy = args.peer_worker
        print(json.dumps(peer_train(data, algo, int(steps), int(seed), policy)))
        return
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.path.insert(0, str(ROOT / "recipes"))  # the studies' docs writer lives beside the recipes
    from studies.docs_fragments import docs_dir_from_args, publish_study

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    env = env_overrides(args)
    overrides = [*args.set, *([f"eval.episodes={args.eval_episodes}"] if args.eval_episodes else [])]
    minari = args.env == "minari"
    metric, better = ("normalised_score", "higher") if minari else ("regret", "lower")
    seeds = [int(x) for x in args.seeds.split(",")] if args.seeds else [args.seed]
    peer_python = None if args.no_peer else ensure_venv(Path(args.venv))
    rows = []
    for algo in args.algos.split(","):
        steps = args.cql_steps if (algo == "cql" and args.cql_steps) else args.steps
        runs = []
        for seed in seeds:
            data_path = out / f"data_seed{seed}.npz"
            run_dir = out / f"project_{algo}_seed{seed}"
            shutil.rmtree(run_dir, ignore_errors=True)  # always trained anew
            trainer, final, own_seconds, transitions = project_run(algo, steps, seed, run_dir, data_path, overrides,
                                                                   env)  # transitions: D's, or S^e's for bc
            run = {"seed": seed, "transitions": transitions, "project": final,
                   "project_s_per_1k": 1000 * own_seconds / steps}
            if peer_python is not None:
                policy_path, peer = _peer_policy(args, peer_python, out, data_path, algo, steps, seed)
                run["d3rlpy"] = score(trainer, policy_path)
                run.update(d3rlpy_s_per_1k=1000 * peer["seconds"] / steps, d3rlpy_config=peer["config"])
            trainer.release()
            runs.append(run)
            sides = [("this project", run["project"])] + ([("d3rlpy", run["d3rlpy"])] if "d3rlpy" in run else [])
            print(f"{LABELS[algo]} seed {seed} ({steps} steps): " + ", ".join(
                f"{name} {fig[metric]:.4g} ± {fig[metric + '_ci']:.3g}" for name, fig in sides), flush=True)
        row = {"algo": algo, "steps": steps, "seeds": seeds, "metric": metric, "runs": runs,
               "transitions": runs[0]["transitions"], "overrides": overrides}
        for side in ("project", "d3rlpy"):
            if side in runs[0]:
                values = [r[side][metric] for r in runs]
                mean, ci = _mean_ci(values) if len(values) > 1 else (values[0], runs[0][side][metric + "_ci"])
                row[f"{side}_{metric}"], row[f"{side}_{metric}_ci"], row[f"{side}_values"] = mean, ci, values
                row[f"{side}_s_per_1k"] = sum(r[f"{side}_s_per_1k"] for r in runs) / len(runs)
        rows.append(row)
        (out / "summary.json").write_text(json.dumps(rows, indent=1, default=str))
    where = (f"Minari {args.expert} + {args.behaviour}" if minari else args.env)
    ci_words = ("a 95% t interval over the seeds" if len(seeds) > 1 else
                "a 95% interval over the evaluation episodes" if minari else
                "a 95% interval over the 1,000 paired evaluation episodes")
    print(f"\n{where}, seeds {seeds}; {metric} ({better} is better, ± {ci_words})\n")
    name = "normalised score" if minari else "regret"
    lines = [f"| method | steps | training rows (seed {seeds[0]}) | d3rlpy 2.8.1 {name} | this project {name} | "
             "s / 1k updates, d3rlpy vs this project |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        peer = (f"{r[f'd3rlpy_{metric}']:.4g} ± {r[f'd3rlpy_{metric}_ci']:.3g}" if f"d3rlpy_{metric}" in r else "–")
        peer_s = f"{r['d3rlpy_s_per_1k']:.1f}" if "d3rlpy_s_per_1k" in r else "–"
        lines.append(f"| {LABELS[r['algo']]} | {r['steps']} | {r['transitions']:,} | {peer} | "
                     f"{r[f'project_{metric}']:.4g} ± {r[f'project_{metric}_ci']:.3g} | {peer_s} vs "
                     f"{r['project_s_per_1k']:.1f} |")
    print("\n".join(lines))
    (out / "tables.md").write_text("\n".join(lines) + "\n")
    if args.publish is None and (minari or args.no_peer or args.set):  # LQR exp1's at the defaults, unless named
        return
    publish_study(args.publish or "peer_d3rlpy", out / "tables.md", docs_dir_from_args(args.docs_dir), seeds=seeds,
                  budget=", ".join(f"{r['steps']} updates ({LABELS[r['algo']]})" for r in rows) + " in both libraries",
                  ci=ci_words, argv=None if argv is None else [sys.argv[0], *argv])


if __name__ == "__main__":
    main()

"""TD3+BC, CQL and IQL of this project against d3rlpy 2.8.1's on the same LQR exp1 data, scored alike.

    python benchmarks/peer_d3rlpy.py                       # 3,000 updates each, seed 0
    python benchmarks/peer_d3rlpy.py --steps 3000 --cql-steps 1000 --algos td3bc,iql,cql

What it does, in order (one process at a time, one torch thread each):

1. builds d3rlpy's own virtual environment (``.peer/d3rlpy-venv``, ignored by git: d3rlpy 2.8.1 pins gymnasium
   1.0.0) with ``python -m venv`` and ``pip install torch==2.13.0 d3rlpy==2.8.1``, unless it is there;
2. exports the recipe's training data D for ``env=lqr_exp1`` and the seed (``WBRMTrainer.q_train_data``: the
   behaviour and expert episodes less the held-out episodes, 18,000 transitions at seed 0) to ``data.npz``;
3. per algo, trains d3rlpy's algorithm on exactly those transitions in a subprocess of that venv (every transition
   one two-observation episode, so each (x, a, r, x') is d3rlpy's transition as stored; ``MinMaxActionScaler`` on
   the env's box [−5, 5]², γ of the env, d3rlpy's defaults otherwise: 2×256 ReLU networks, batch 256, its learning
   rates and τ) and saves its greedy policy as TorchScript (d3rlpy's ``save_policy``, the action scaler included);
4. trains this project's algo on the same data (``algo=<name>``, the recipe's defaults, ``q.steps`` = the budget);
5. scores both policies with this project's paired regret (``LQRTask``'s evaluator: 1,000 paired episodes against
   the exact optimum, the recipe's ``eval.seed``) and prints the table, with the seconds per 1,000 updates of each
   (d3rlpy: its ``fit`` loop; this project: the trainer's update steps, batch sampling included; evaluations out).

Everything is written under ``--out`` (default ``results/peer_d3rlpy``); ``summary.json`` holds the table. d3rlpy's
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
LABELS = {"td3bc": "TD3+BC", "cql": "CQL", "iql": "IQL"}


# ---------------------------------------------------------------------- d3rlpy's side (runs in its own venv)
def peer_train(data_path: str, algo: str, steps: int, seed: int, policy_path: str) -> dict:
    """Train d3rlpy's ``algo`` on the exported transitions; save its greedy policy (TorchScript). Runs in the
    d3rlpy venv: imports nothing of this project."""
    import numpy as np
    import torch

    import d3rlpy
    from d3rlpy.dataset import Episode, InfiniteBuffer, ReplayBuffer
    from d3rlpy.preprocessing import MinMaxActionScaler

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
    scaler = MinMaxActionScaler(minimum=low, maximum=high)
    gamma = float(data["gamma"])
    config = {
        "td3bc": lambda: d3rlpy.algos.TD3PlusBCConfig(action_scaler=scaler, gamma=gamma),
        "cql": lambda: d3rlpy.algos.CQLConfig(action_scaler=scaler, gamma=gamma),
        "iql": lambda: d3rlpy.algos.IQLConfig(action_scaler=scaler, gamma=gamma),
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


def base_overrides(seed: int, steps: int, algo: str) -> list[str]:
    return ["env=lqr_exp1", f"seed={seed}", f"algo={algo}", f"q.steps={steps}", f"q.eval_every={steps}",
            "checkpoint_every=0", "plots=false", "logger=none"]


def export_data(trainer, path: Path) -> int:
    import numpy as np

    d, spec = trainer.q_train_data, trainer.action_spec
    np.savez(path, observation=d["observation"].numpy(), action=d["action"].numpy(),
             reward=d["next", "reward"].numpy(), next_observation=d["next", "observation"].numpy(),
             terminated=d["next", "terminated"].numpy(), action_low=spec.space.low.numpy(),
             action_high=spec.space.high.numpy(), gamma=np.float64(trainer.gamma))
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


def project_run(algo: str, steps: int, seed: int, run_dir: Path, data_path: Path | None):
    """Train this project's ``algo``; returns (trainer, final figures, seconds of the update steps)."""
    import torch

    from torchrl_wbrm.training import WBRMTrainer

    torch.set_num_threads(1)
    cfg = compose(base_overrides(seed, steps, algo))
    trainer = WBRMTrainer(cfg, run_dir, progress=False)
    if data_path is not None:
        export_data(trainer, data_path)
    seconds = [0.0]
    q_step = trainer._q_step

    def timed(step: int) -> dict:
        start = time.perf_counter()
        out = q_step(step)
        seconds[0] += time.perf_counter() - start
        return out

    trainer._q_step = timed
    results = trainer.run()
    return trainer, results["final"], seconds[0]


def score(trainer, policy_path: Path) -> dict:
    """This project's paired regret of a TorchScript policy (observation -> action), by the trainer's evaluator."""
    import torch
    from tensordict.nn import TensorDictModule

    scripted = torch.jit.load(str(policy_path))
    policy = TensorDictModule(lambda x: scripted(x.float()), in_keys=["observation"], out_keys=["action"])
    ec = trainer.cfg.eval
    with torch.no_grad():
        return trainer.evaluator.evaluate(policy, episodes=ec.episodes, seed=ec.seed)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=3000, help="updates per algo, both libraries (default 3000)")
    parser.add_argument("--cql-steps", type=int, default=None, help="CQL's budget, both libraries (default --steps)")
    parser.add_argument("--algos", default=",".join(ALGOS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(ROOT / "results" / "peer_d3rlpy"))
    parser.add_argument("--venv", default=str(VENV))
    parser.add_argument("--rerun-peer", action="store_true",
                        help="train d3rlpy again even where its run on the same data, budget and seed is saved")
    parser.add_argument("--peer-worker", nargs=5, metavar=("DATA", "ALGO", "STEPS", "SEED", "POLICY"),
                        help=argparse.SUPPRESS)
    parser.add_argument("--docs-dir", default=None, metavar="PATH",  # the peer worker's venv has no torchrl_wbrm
                        help="the Sphinx docs folder that receives the table (results/_generated/peer_d3rlpy.md); "
                             "default: the clone's docs/; 'none': skip")
    args = parser.parse_args(argv)
    if args.peer_worker:
        data, algo, steps, seed, policy = args.peer_worker
        print(json.dumps(peer_train(data, algo, int(steps), int(seed), policy)))
        return
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from torchrl_wbrm.training.docs_fragments import docs_dir_from_args, publish_study

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    peer_python = ensure_venv(Path(args.venv))
    data_path = out / "data.npz"
    rows = []
    for algo in args.algos.split(","):
        steps = args.cql_steps if (algo == "cql" and args.cql_steps) else args.steps
        run_dir = out / f"project_{algo}"
        shutil.rmtree(run_dir, ignore_errors=True)  # always trained anew
        trainer, final, own_seconds = project_run(algo, steps, args.seed, run_dir, data_path)
        data_sha = data_digest(data_path)
        policy_path = out / f"d3rlpy_{algo}_{steps}steps_seed{args.seed}.pt"
        record = policy_path.with_suffix(".json")
        peer = json.loads(record.read_text()) if record.is_file() and policy_path.is_file() else None
        if peer is None or peer.get("data_sha256") != data_sha or args.rerun_peer:
            proc = subprocess.run([str(peer_python), __file__, "--peer-worker", str(data_path), algo, str(steps),
                                   str(args.seed), str(policy_path)], capture_output=True, text=True,
                                  env={**os.environ, "OMP_NUM_THREADS": "1"})
            if proc.returncode:
                how = (f"killed by signal {-proc.returncode}" if proc.returncode < 0
                       else f"exit code {proc.returncode}")
                raise SystemExit(f"d3rlpy {algo} failed ({how}, in {peer_python}):\n{proc.stderr[-4000:]}")
            peer = {**json.loads(proc.stdout.strip().splitlines()[-1]), "data_sha256": data_sha}
            record.write_text(json.dumps(peer, indent=1, default=str))
        else:
            print(f"d3rlpy {algo}: its run on the same data, budget and seed is reused ({record})", flush=True)
        peer_score = score(trainer, policy_path)
        row = {"algo": algo, "steps": steps, "seed": args.seed, "transitions": int(trainer.q_train_data.shape[0]),
               "d3rlpy_regret": peer_score["regret"], "d3rlpy_regret_ci": peer_score["regret_ci"],
               "project_regret": final["regret"], "project_regret_ci": final["regret_ci"],
               "d3rlpy_s_per_1k": 1000 * peer["seconds"] / steps, "project_s_per_1k": 1000 * own_seconds / steps,
               "d3rlpy_config": peer["config"]}
        rows.append(row)
        print(f"{LABELS[algo]}: d3rlpy {row['d3rlpy_regret']:.4f} ± {row['d3rlpy_regret_ci']:.4f}, this project "
              f"{row['project_regret']:.4f} ± {row['project_regret_ci']:.4f} ({steps} steps; s/1k updates "
              f"{row['d3rlpy_s_per_1k']:.1f} vs {row['project_s_per_1k']:.1f})", flush=True)
        (out / "summary.json").write_text(json.dumps(rows, indent=1, default=str))
    print(f"\nLQR exp1, seed {args.seed}, {rows[0]['transitions']} training transitions; paired regret (± 95% CI over "
          f"1,000 paired episodes)\n")
    lines = ["| method | steps | d3rlpy 2.8.1 | this project | s / 1k updates (d3rlpy vs this project) |",
             "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {LABELS[r['algo']]} | {r['steps']} | {r['d3rlpy_regret']:.4f} ± {r['d3rlpy_regret_ci']:.4f} | "
                     f"{r['project_regret']:.4f} ± {r['project_regret_ci']:.4f} | {r['d3rlpy_s_per_1k']:.1f} vs "
                     f"{r['project_s_per_1k']:.1f} |")
    print("\n".join(lines))
    (out / "tables.md").write_text("\n".join(lines) + "\n")
    publish_study("peer_d3rlpy", out / "tables.md", docs_dir_from_args(args.docs_dir), seeds=[args.seed],
                  budget=", ".join(f"{r['steps']} updates ({LABELS[r['algo']]})" for r in rows) + " in both libraries",
                  ci="a 95% interval over the 1,000 paired evaluation episodes",
                  argv=None if argv is None else [sys.argv[0], *argv])


if __name__ == "__main__":
    main()

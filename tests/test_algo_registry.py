"""One file per algorithm (torchrl_wbrm/algos/), one task object per env (torchrl_wbrm/tasks/), and the recipes'
lists read from them: an algorithm registered anywhere is a valid ``algo=`` of the recipe, has its Hydra node and is
listed by the studies and the configuration guide (docs/guides/configuration.md)."""
from __future__ import annotations

import ast
import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from torchrl_wbrm.algos import ALGOS, algo_names, algo_table, build_algo, get_algo, register_algo, unregister_algo
from torchrl_wbrm.algos.brm import build_brm
from torchrl_wbrm.configs import CONFIG_DIR
from torchrl_wbrm.tasks import EnvConfig
from torchrl_wbrm.tasks import TASKS, get_task
from torchrl_wbrm.training.config import BaselinesConfig, WBRMConfig, register_configs, validate_config
from torchrl_wbrm.training.plots import LOSS_TITLES

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "torchrl_wbrm"

BUILT_IN = {"wbrm", "brm", "bc", "td3bc", "ddpg", "cql", "iql", "dqn", "fqi", "mabo"}


def _compose(*overrides: str):
    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return OmegaConf.to_object(compose("wbrm_offline", overrides=list(overrides)))


def test_every_algorithm_is_one_file_of_the_package():
    files = {p.stem for p in (PACKAGE / "algos").glob("*.py") if not p.stem.startswith("_")} - {"base", "registry"}
    assert files == set(ALGOS) == BUILT_IN
    for name, spec in ALGOS.items():
        assert spec.build.__module__ == f"torchrl_wbrm.algos.{name}"  # registered in its own file


@pytest.mark.parametrize("name", sorted(BUILT_IN))
def test_every_algo_has_a_config_node_that_the_recipe_composes(name):
    cfg = _compose(f"algo={name}")
    assert cfg.algo == name
    spec = get_algo(name)
    if spec.config is not None:  # the node sets baselines.<name> to the dataclass's defaults
        assert getattr(cfg.baselines, name) == spec.config()
    validate_config(cfg)


def test_no_yaml_shadows_the_algo_nodes():
    """The ``algo`` group is the registry's (``register_configs``); a ``configs/algo/<name>.yaml`` would take the
    node's place, so there is none."""
    assert not list((CONFIG_DIR / "algo").glob("*.yaml"))


def test_baselines_config_holds_every_algo_with_settings():
    fields = {f.name: f.type for f in dataclasses.fields(BaselinesConfig)}
    assert fields == {n: s.config for n, s in ALGOS.items() if s.config is not None}
    assert set(fields) == {"bc", "td3bc", "ddpg", "cql", "iql", "dqn", "fqi", "mabo"}


@pytest.fixture
def toy_algo():
    """A toy algorithm registered the way an algo file does it (unregistered afterwards)."""
    register_algo("toy", loss="the unweighted residual", reference="a test", loss_title="toy: losses")(build_brm)
    try:
        yield
    finally:
        unregister_algo("toy")
    assert "toy" not in ALGOS


def test_a_registered_algo_is_valid_and_listed(toy_algo):
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(WBRMConfig), {"algo": "toy"}))
    validate_config(cfg)  # a valid algo= now
    assert "toy" in algo_names() and LOSS_TITLES["toy"] == "toy: losses"
    assert "| `toy` | the unweighted residual | a test |" in algo_table()
    sys.path.insert(0, str(ROOT / "recipes"))
    try:
        import paper_tables
    finally:
        sys.path.remove(str(ROOT / "recipes"))
    assert "toy" in paper_tables.available_algos()
    # its Hydra node: algo=toy composes (the schema's baselines hold the algos registered at import)
    register_configs()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        assert compose("wbrm_offline", overrides=["algo=toy"]).algo == "toy"


def test_a_registered_algo_runs_in_the_trainer(toy_algo, tmp_path):
    from torchrl_wbrm.training import WBRMTrainer

    cfg = {"algo": "toy", "env": {"lqr_data": {"behaviour_episodes": 20, "expert_episodes": 10, "parallel_envs": 10}},
           "q": {"steps": 4, "eval_every": 4, "num_cells": [8], "actor_num_cells": [8]}, "logger": {"backend": ""},
           "eval": {"episodes": 10, "train_episodes": 10, "q_samples": 100}, "plots": False, "checkpoint_every": 0}
    results = WBRMTrainer(cfg, tmp_path, progress=False).run()
    assert results["algo"] == "toy" and results["status"] == "finished" and "regret" in results["final"]


def test_unknown_and_duplicate_names_are_clear_errors():
    with pytest.raises(ValueError, match=r"algo='sac' is not known: choose one of \['bc', 'brm'"):
        get_algo("sac")
    with pytest.raises(ValueError, match="algo='sac' is not known"):
        build_algo("sac", None)
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(WBRMConfig), {"algo": "sac"}))
    with pytest.raises(ValueError, match=r"algo='sac' is not allowed: choose one of \[.*'wbrm'"):
        validate_config(cfg)
    with pytest.raises(ValueError, match="'wbrm' is registered already"):
        register_algo("wbrm")(build_brm)
    with pytest.raises(ValueError, match="must be an identifier"):
        register_algo("my algo")
    with pytest.raises(TypeError, match="config must be a dataclass"):
        register_algo("mine", config=dict)


def test_settings_of_an_algo_registered_after_the_schema_are_a_clear_error():
    """The schema (``baselines.<name>``) is built when torchrl_wbrm.training.config is imported; an algo with
    settings registered later cannot be composed, and ``register_configs`` says so."""

    @dataclasses.dataclass
    class LateConfig:
        gain: float = 1.0

    register_algo("late", config=LateConfig)(build_brm)
    try:
        with pytest.raises(ValueError, match=r"algo 'late' was registered after .* baselines.late are not in it"):
            register_configs()
    finally:
        unregister_algo("late")
    register_configs()


def test_an_algos_own_settings_are_checked_by_its_file():
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(WBRMConfig),
                                              {"baselines": {"mabo": {"adversary": "quadratic"}}}))
    with pytest.raises(ValueError, match=r"baselines.mabo.adversary='quadratic' is not allowed: choose one of "
                                         r"\['network', 'linear'\]"):
        validate_config(cfg)


def test_the_configuration_guide_lists_the_registered_algorithms():
    text = (ROOT / "docs" / "guides" / "configuration.md").read_text()
    block = re.search(r"<!-- algos -->\n(.*?)\n<!-- /algos -->", text, re.S)
    assert block is not None, "docs/guides/configuration.md has no <!-- algos --> block"
    assert block.group(1).strip() == algo_table()


# ---------------------------------------------------------------------- tasks
@pytest.mark.parametrize("kind, gamma", [("lqr", 0.9), ("mountain_car", 0.9999), ("minari", 0.99)])
def test_every_env_kind_is_a_task(kind, gamma):
    task = get_task(EnvConfig(name=kind, kind=kind))
    assert task.kind == kind and task.gamma(None) == pytest.approx(gamma) and task.gamma(0.5) == 0.5
    assert task.has_exact_ratio == (kind == "lqr") and task.collects_data == (kind != "minari")
    with pytest.raises(ValueError, match="env.kind='gridworld' is not known"):
        get_task({"kind": "gridworld"})


def test_nothing_but_the_tasks_branches_on_the_env_kind():
    """``get_task`` is the one place that maps ``env.kind`` to its facts."""
    proc = subprocess.run(["grep", "-rnE", r"is_lqr|\.kind ?[!=]=|== \"(mountain_car|minari|lqr)\"", "--include=*.py",
                           str(PACKAGE)], capture_output=True, text=True)
    # data/minari_examples.py's command line picks which example datasets to write (not an env of a run)
    hits = [line for line in proc.stdout.splitlines() if "/torchrl_wbrm/tasks/" not in line and "minari_examples.py" not in line]
    assert hits == [] and set(TASKS) == {"lqr", "mountain_car", "minari"}


def _runtime_imports(tree: ast.AST):
    """The modules ``tree`` imports when run (an ``if TYPE_CHECKING:`` block's, for annotations only, left out)."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            continue
        if isinstance(node, ast.ImportFrom) and node.module:
            yield node.module
        elif isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        yield from _runtime_imports(node)


#: the package's floors, lowest first: a floor imports only from its own and the floors below it
FLOORS = (("_console", "_devices", "_files", "keys"), ("envs",), ("policies", "modules"), ("objectives",), ("evaluation",),
          ("data",), ("tasks",), ("ratio",), ("ope",), ("algos",), ("training",), ("cli",), ("__main__",))


def test_every_floor_imports_only_from_the_floors_below_it():
    level = {name: i for i, floor in enumerate(FLOORS) for name in floor}
    top = {p.stem if p.is_file() else p.name for p in PACKAGE.iterdir()
           if (p.is_dir() and (p / "__init__.py").exists()) or (p.suffix == ".py" and p.stem != "__init__")}
    assert top == set(level), f"a floor of the package is not listed in FLOORS: {sorted(top ^ set(level))}"
    for name, floor in level.items():
        root = PACKAGE / name
        for path in (root.rglob("*.py") if root.is_dir() else [root.with_suffix(".py")]):
            for module in _runtime_imports(ast.parse(path.read_text())):
                assert not module.startswith("recipes"), (path, module)
                parts = module.split(".")
                if parts[0] == "torchrl_wbrm" and len(parts) > 1 and parts[1] in level:
                    assert level[parts[1]] <= floor, f"{path.relative_to(PACKAGE)} imports {module}, a higher floor"


# ---------------------------------------------------------------------- recipes: wiring only
def test_no_recipe_imports_another_and_the_studies_share_one_runner():
    recipes = {p.stem: p for p in (ROOT / "recipes").glob("*.py")}
    for name, path in recipes.items():
        imported = set(_runtime_imports(ast.parse(path.read_text())))
        assert not imported & set(recipes), f"recipes/{name}.py imports {imported & set(recipes)}"
    for study in ("paper_tables", "weighting_study", "ablations", "convergence_study", "q_accuracy_study"):
        text = recipes[study].read_text()
        assert "run_cells(" in text and "joblib" not in text and "subprocess" not in text, study


def test_the_studies_budgets_are_read_from_the_yaml():
    """``configs/study_budgets.yaml`` holds the studies' budgets; an alias splices another budget in at its place."""
    from studies.runs import study_budget

    assert study_budget("table") == ["q.num_cells=[128,128]", "q.actor_num_cells=[128,128]", "q.steps=2000",
                                     "q.eval_every=500", "eval.train_episodes=200", "baselines.cql.num_random=4"]
    quiet = study_budget("quiet")
    assert quiet == ["logger=none", "plots=false", "checkpoint_every=0"] == study_budget("quick")[-3:]
    assert study_budget("weighting") == ["ratio.steps=1000", "q.steps=2000", "q.eval_every=2000", "eval.episodes=1000",
                                         "eval.q_samples=5000", *quiet]
    assert study_budget("q_accuracy") == ["q.eval_every=1500", "eval.episodes=1000", "eval.q_samples=5000", *quiet]
    assert study_budget("convergence")[:3] == quiet and "ratio.clip=null" in study_budget("convergence")
    names = OmegaConf.load(CONFIG_DIR / "study_budgets.yaml").keys()
    assert sorted(names) == ["convergence", "convergence_quick", "q_accuracy", "quick", "quiet", "table",
                             "table_quick", "weighting"]
    for name in names:
        budget = study_budget(name)
        assert budget and all(isinstance(o, str) and "=" in o for o in budget), name
        _compose(*budget)  # each composes with the recipe's config
    with pytest.raises(ValueError, match="no study budget 'tables'.*quick, table"):
        study_budget("tables")


def _in_this_process(cmd, *, check, cwd, env):
    """``subprocess.run`` of ``python <script> <args>`` through :func:`tests.inprocess.run_script`."""
    from tests.inprocess import run_script

    assert cmd[0] == sys.executable, cmd
    proc = run_script(cmd[1], *cmd[2:], cwd=cwd, env=env)
    if check and proc.returncode:
        raise subprocess.CalledProcessError(proc.returncode, cmd, proc.stdout, proc.stderr)
    return proc


def test_the_runner_runs_cells_through_a_hydra_launcher(tmp_path, monkeypatch):
    """``run_cells(..., launcher=...)``: one Hydra multirun per cell (here Hydra's joblib launcher), each run in its
    cell directory with the cell's labels in its results, as a local run writes them; finished runs are skipped. The
    multirun command the runner starts runs in this process (tests/test_launchers.py starts one as its own python)."""
    from studies import runs
    from studies.runs import cell_dir, run_cells, study_budget

    monkeypatch.setattr(runs, "subprocess", SimpleNamespace(run=_in_this_process))

    cell = {"block": "b", "env": "lqr_exp1", "setting": "s", "method": "brm", "overrides": ["algo=brm"]}
    budget = [*study_budget("quick"), "q.steps=4", "q.eval_every=4", "eval.episodes=10", "eval.train_episodes=10",
              "eval.offline_value=false"]
    run_cells([cell], [0, 1], budget, tmp_path, launcher="joblib", launcher_args=["hydra.launcher.n_jobs=1"])
    for seed in (0, 1):
        results = json.loads((cell_dir(tmp_path, cell, seed) / "results.json").read_text())
        assert results["seed"] == seed and results["algo"] == "brm" and results["config"]["q"]["steps"] == 4
        assert results["study"] == {"block": "b", "env": "lqr_exp1", "setting": "s", "method": "brm"}
    run_cells([cell], [0, 1], budget, tmp_path, launcher="no_such_launcher")  # all done: nothing is launched
    # a finished run is reused only under the settings it ran with: the launched runs' saved configs equal the
    # runner's composition (above), and another budget is refused by name, not reported as this one's
    with pytest.raises(ValueError, match=r"q\.steps: 4 -> 5.*another directory"):
        run_cells([cell], [0, 1], [*budget, "q.steps=5"], tmp_path, launcher="no_such_launcher")


def test_a_finished_run_is_reused_only_under_its_own_settings(tmp_path):
    """``run_overrides`` reads a finished run back without training, if it ran with the same config; a changed
    setting that changes a figure is refused by name, one that cannot (threads, plots, the logger) is not."""
    from studies.runs import compose_recipe_config, run_overrides
    from torchrl_wbrm.training.config import config_as_dict

    overrides = ["algo=brm", "env=lqr_exp1", "q.steps=7", "logger=none", "plots=false"]
    saved = {"status": "finished", "final": {"regret": 0.5}, "config": config_as_dict(compose_recipe_config(overrides))}
    (tmp_path / "results.json").write_text(json.dumps(saved))
    assert run_overrides(overrides, tmp_path)["final"] == {"regret": 0.5}  # read back, not trained
    assert run_overrides([*overrides, "plots=true", "logger=csv"], tmp_path)["final"] == {"regret": 0.5}
    with pytest.raises(ValueError, match=r"results\.json holds a finished run with other settings: "
                                         r"baselines\.cql\.with_lagrange: False -> True"):
        run_overrides([*overrides, "baselines.cql.with_lagrange=true"], tmp_path)
    with pytest.raises(ValueError, match=r"q\.steps: 7 -> 8; seed: 0 -> 3"):
        run_overrides([*overrides, "q.steps=8", "seed=3"], tmp_path)
    (tmp_path / "results.json").write_text(json.dumps({"status": "finished"}))
    with pytest.raises(ValueError, match="without the config they ran with"):
        run_overrides(overrides, tmp_path)


"""A non-editable install: the wheel ships the configs (the top-level ``configs/``, mapped to ``torchrl_wbrm.configs``), and its ``wbrm-offline`` command and ``python -m torchrl_wbrm``
run the recipe from any directory.

The wheel is built from a copy of the package sources (no build isolation, nothing downloaded) and installed with
``--no-deps --no-index`` into a fresh virtual environment that sees this environment's site-packages through a
``.pth`` file (torch and the other dependencies are not installed again); the editable install of this clone is not
visible there (``.pth`` files of an added directory are not executed), so the commands run the installed copy.

The install-and-run test (marker ``packaging``, about 30 s) is deselected by the suite's default ``-m "not packaging"``
(pyproject's ``addopts``); CI runs it as its own step: ``python -m pytest -q tests/test_packaging.py -m packaging``.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

TINY = [
    "env.lqr_data.behaviour_episodes=40", "env.lqr_data.expert_episodes=20", "env.lqr_data.parallel_envs=20",
    "ratio.steps=10", "ratio.eval_every=5", "ratio.num_cells=[8,8]", "q.steps=10", "q.eval_every=5",
    "q.num_cells=[8,8]", "q.actor_num_cells=[8,8]", "eval.offline_value=false", "eval.episodes=10", "eval.train_episodes=10",
    "eval.q_samples=100", "logger=none", "plots=false",
]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The project's wheel, built offline from a copy of its sources."""
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "setup.py", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, src / name)
    for folder in ("torchrl_wbrm", "configs"):
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = tmp_path_factory.mktemp("dist")
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                           "-q", "-w", str(out), str(src)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (whl,) = out.glob("torchrl_wbrm-*.whl")
    return whl


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> Path:
    """A fresh virtual environment with the wheel installed (not editable); returns its ``bin`` folder."""
    env_dir = tmp_path_factory.mktemp("venv")
    venv.create(env_dir, with_pip=False, symlinks=True)
    python = env_dir / "bin" / "python"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    # this environment's dependencies, after the fresh environment's own site-packages on sys.path
    Path(purelib, "_host_site_packages.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    proc = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index",
                           "-q", str(wheel)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return env_dir / "bin"


def test_the_wheel_ships_the_configs_and_the_commands(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    # the clone's top-level configs/ is the package torchrl_wbrm.configs in the wheel
    configs = sorted(f"torchrl_wbrm/configs/{p.relative_to(ROOT / 'configs').as_posix()}"
                     for p in (ROOT / "configs").rglob("*.yaml"))
    assert {"torchrl_wbrm/configs/wbrm_offline.yaml", "torchrl_wbrm/configs/env/lqr_exp1.yaml"} <= set(configs)
    assert [c for c in configs if c not in names] == []  # every config of the source tree, group folders included
    assert "torchrl_wbrm/configs/__init__.py" in names and not [n for n in names if n.startswith("configs/")]
    assert "torchrl_wbrm/cli.py" in names and "torchrl_wbrm/__main__.py" in names
    # the library only: the studies' runner and docs writer stay in the clone (recipes/studies/)
    assert not [n for n in names if n.endswith(("/runs.py", "/docs_fragments.py")) or n.startswith("studies/")]
    (entry_points,) = [n for n in names if n.endswith(".dist-info/entry_points.txt")]
    text = zipfile.ZipFile(wheel).read(entry_points).decode()
    assert "wbrm-offline = torchrl_wbrm.cli:wbrm_offline" in text
    assert "wbrm-make-dataset = torchrl_wbrm.cli:make_dataset" in text


@pytest.mark.packaging  # about 30 s: left out of the suite by pyproject's addopts; .ci/run runs it as its own step
def test_installed_command_runs_the_recipe_from_another_directory(installed, tmp_path):
    """``wbrm-offline`` and ``python -m torchrl_wbrm`` from a directory with no clone in it, on the installed copy."""
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.update(OMP_NUM_THREADS="1", MPLBACKEND="Agg", WANDB_MODE="offline", PATH=f"{installed}:{env.get('PATH', '')}")
    where = subprocess.run([str(installed / "python"), "-c", "import torchrl_wbrm; print(torchrl_wbrm.__file__)"],
                           cwd=work, env=env, capture_output=True, text=True, check=True).stdout.strip()
    assert not Path(where).is_relative_to(ROOT) and Path(where).is_relative_to(installed.parent), where
    configs = subprocess.run([str(installed / "python"), "-c", "import torchrl_wbrm.configs as c; print(c.CONFIG_DIR)"],
                             cwd=work, env=env, capture_output=True, text=True, check=True).stdout.strip()
    assert Path(configs) == Path(where).parent / "configs" and (Path(configs) / "env" / "lqr_exp1.yaml").is_file()
    for name, cmd in (("console", [str(installed / "wbrm-offline")]),
                      ("module", [str(installed / "python"), "-m", "torchrl_wbrm"])):
        proc = subprocess.run([*cmd, *TINY, f"seed={len(name)}"], cwd=work, env=env, capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode == 0, f"{name}:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
        (run_dir,) = (work / "outputs" / "wbrm_offline" / "lqr_exp1").glob(f"*_seed{len(name)}")
        assert (run_dir / "results.json").is_file() and (run_dir / "checkpoint.pt").is_file()
        assert (run_dir / ".hydra" / "config.yaml").is_file()
        assert "run directory:" in proc.stdout and run_dir.name in proc.stdout.split("run directory:")[-1]


def test_a_clone_imports_its_top_level_configs():
    """In a clone (an editable install, as the README sets up), ``torchrl_wbrm.configs`` is the top-level ``configs/``:
    the build's package-dir mapping, resolved by the editable install's finder."""
    import torchrl_wbrm
    from torchrl_wbrm.configs import CONFIG_DIR

    assert Path(torchrl_wbrm.__file__).resolve().is_relative_to(ROOT), (
        f"torchrl_wbrm is imported from {torchrl_wbrm.__file__}, not from this clone: install it as the README says")
    assert CONFIG_DIR == ROOT / "configs" and (CONFIG_DIR / "wbrm_offline.yaml").is_file()
    assert not (ROOT / "torchrl_wbrm" / "configs").exists()

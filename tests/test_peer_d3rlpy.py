"""``benchmarks/peer_d3rlpy.py``'s own venv: a venv that exists but cannot import d3rlpy is not used as it is (pip's
"already satisfied" would not repair a truncated library, which made ``import numpy`` die of SIGBUS here), and one
the script does not own is refused by name. Building a venv needs PyPI, so only the refusals are tested here."""
from __future__ import annotations

import importlib.util
import stat
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _peer():
    spec = importlib.util.spec_from_file_location("peer_d3rlpy", ROOT / "benchmarks" / "peer_d3rlpy.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _fake_venv(root: Path, body: str) -> Path:
    python = root / "bin" / "python"
    python.parent.mkdir(parents=True)
    python.write_text(f"#!/bin/sh\n{body}\n")
    python.chmod(python.stat().st_mode | stat.S_IEXEC)
    return root


@pytest.mark.parametrize("body, code", [("exit 1", "exit code 1"), ("kill -BUS $$", "exit code -7")])
def test_a_broken_venv_that_is_not_the_scripts_own_is_refused_by_name(tmp_path, body, code):
    peer = _peer()
    venv = _fake_venv(tmp_path / "my-venv", body)
    with pytest.raises(SystemExit, match=rf"{venv} exists but its python fails `import d3rlpy, torch`.*\({code}\)"):
        peer.ensure_venv(venv)
    assert (venv / "bin" / "python").is_file()  # not deleted: it is not the script's own


def test_a_working_venv_is_used_as_it_is(tmp_path):
    venv = _fake_venv(tmp_path / "ok-venv", "exit 0")
    assert _peer().ensure_venv(venv) == venv / "bin" / "python"


@pytest.mark.parametrize("algo", ["iql", "bc"])
def test_the_export_holds_what_each_algo_trains_on(tmp_path, single_thread, algo):
    """IQL's export is D (``q_train_data``) as it is; BC's is S^e, the rows it clones, every row terminal with a
    zero reward, so that d3rlpy keeps each row as one transition."""
    import numpy as np
    import torch

    from tests.test_training import tiny_config
    from torchrl_wbrm.training import WBRMTrainer

    trainer = WBRMTrainer(tiny_config(algo=algo), tmp_path / "run", progress=False)
    n = _peer().export_data(trainer, tmp_path / "data.npz")
    with np.load(tmp_path / "data.npz") as exported:
        data = dict(exported)
    source = trainer.datasets.expert_samples[:] if algo == "bc" else trainer.q_train_data
    assert n == source.shape[0] == data["observation"].shape[0]
    torch.testing.assert_close(torch.from_numpy(data["action"]), source["action"])
    if algo == "bc":
        assert data["terminated"].all() and not data["reward"].any()
    else:
        torch.testing.assert_close(torch.from_numpy(data["reward"]), source["next", "reward"])
        assert data["terminated"].shape == (n, 1)


@pytest.mark.parametrize("name", ["../x", "a/b", "Locomotion", "", "x.md"])
def test_a_fragment_name_that_is_not_a_plain_name_is_refused(name, capsys):
    """``--publish NAME`` names a file in the docs: anything but lower-case letters, digits and '_' is refused in one
    line before anything runs."""
    with pytest.raises(SystemExit):
        _peer().main(["--publish", name, "--no-peer", "--out", "/nonexistent/never-made"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--publish" in err and "lower-case letters, digits and '_' only" in err
    assert not Path("/nonexistent/never-made").exists()

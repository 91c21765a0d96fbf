"""The examples/ scripts run (``--quick``) and learn: each asserts an outcome against a computed reference, with a
margin, not only that the script finished.

All six run in the test process (one torch/torchrl import instead of six), each through
:func:`tests.inprocess.run_script` as ``python examples/<name>.py --quick`` would run it; their printed output is
parsed.
"""
from __future__ import annotations

import os
import re
import time
from pathlib import Path

import pytest

from tests.inprocess import run_script
from tests.references import reference_regrets

#: one xdist worker runs this module (``pytest -n 2 --dist loadfile``): its shared runs are computed once

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ["weighted_td3bc_lqr", "wbrm_ddpg_lqr", "wbrm_dqn_cartpole", "weighted_ddpg_lqr", "weighted_iql_lqr",
            "wbrm_minari_agent"]


@pytest.fixture(scope="session")
def outputs(tmp_path_factory):
    log_dir = tmp_path_factory.mktemp("example_logs")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = {}
    for name in EXAMPLES:
        start = time.process_time()
        proc = run_script(ROOT / "examples" / f"{name}.py", "--quick", "--log-dir", log_dir / name, env=env)
        assert proc.returncode == 0, f"{name}:\n{proc.stderr[-3000:]}"
        print(f"{name}: {time.process_time() - start:.1f} s CPU\n{proc.stdout}")
        assert any((log_dir / name).rglob("*.csv")), f"{name} wrote no CSV log"  # TorchRL's CSVLogger was used
        result[name] = proc.stdout
    return result


def _figure(text: str, label: str, what: str = "regret") -> float:
    match = re.search(rf"^{re.escape(label)}\s+.*?{what}\s+(-?[0-9.]+)", text, re.MULTILINE)
    assert match, (label, text)
    return float(match.group(1))


@pytest.fixture(scope="session")
def regrets():
    """Exact regrets of reference policies on LQR exp1: the behaviour mean ``a = −0.5Kx`` and the zero action."""
    return reference_regrets("exp1")


@pytest.mark.slow
def test_weighted_td3bc_learns(outputs, regrets):
    """TorchRL's TD3BCLoss with ŵ as priority_weight: the quick run's regret is below half the zero action's (the
    actor starts at a ≈ 0). It learns slowly: TD3+BC's cloning term (an unweighted batch mean in TorchRL) pulls the
    actor towards the behaviour mean a = −0.5Kx, whose exact regret the script prints beside it."""
    text = outputs["weighted_td3bc_lqr"]
    weighted = _figure(text, "ŵ-weighted TD3+BC")
    assert weighted < regrets["zero_action"] / 2, weighted
    assert _figure(text, "behaviour mean") == pytest.approx(regrets["behaviour_mean"], abs=1e-4)


@pytest.mark.slow
def test_wbrm_in_a_ddpg_loop_beats_the_behaviour_policy(outputs, regrets):
    """WeightedBellmanLoss as the critic loss of an offline DDPG loop: regret below half the behaviour mean's."""
    regret = _figure(outputs["wbrm_ddpg_lqr"], "WBRM (DDPG loop)")
    assert regret < regrets["behaviour_mean"] / 2, regret


@pytest.mark.slow
def test_discrete_wbrm_on_cartpole_beats_the_behaviour_data(outputs):
    """WeightedBellmanLoss with a QValueActor: the greedy policy's return is at least twice the behaviour data's
    (``--quick`` trains it alone; the full run reports TorchRL's DQNLoss on the same data beside it)."""
    text = outputs["wbrm_dqn_cartpole"]
    behaviour = float(re.search(r"behaviour return ([0-9.]+)", text).group(1))
    wbrm = _figure(text, "WeightedBellmanLoss", "greedy return")
    assert behaviour < 100 and wbrm > 2 * behaviour, (behaviour, wbrm)


@pytest.mark.slow
def test_weighted_ddpg_learns(outputs, regrets):
    """TorchRL's DDPGLoss with ŵ as priority_weight: regret below half the behaviour mean's."""
    weighted = _figure(outputs["weighted_ddpg_lqr"], "ŵ-weighted DDPG")
    assert weighted < regrets["behaviour_mean"] / 2, weighted


@pytest.mark.slow
def test_weighted_iql_learns(outputs, regrets):
    """TorchRL's IQLLoss with ŵ through WeightedLoss: below the behaviour mean's regret by a margin of a fifth (the
    actor starts near the zero action, regret 0.36). ``--quick`` trains the weighted one only (the full run reports
    its unweighted twin beside it); that ŵ reaches IQL's terms is tests/test_weighted_loss.py's."""
    text = outputs["weighted_iql_lqr"]
    weighted = _figure(text, "ŵ-weighted IQL")
    assert weighted < 0.8 * regrets["behaviour_mean"], weighted
    assert not re.search(r"^IQL\s", text, re.MULTILINE), text  # the twin is not trained in --quick
    assert _figure(text, "behaviour mean") == pytest.approx(regrets["behaviour_mean"], abs=1e-4)


def test_the_composed_minari_agent_runs_and_selects_by_the_held_out_residual(outputs):
    """examples/wbrm_minari_agent.py --quick (300 updates: too few to learn the swing-up; the full run's score is in
    the tutorial): it reads the example pair (an expert far above its behaviour data), delivers the actor of one of
    its two evaluations, the one of lowest held-out weighted residual, and scores it on the env."""
    text = outputs["wbrm_minari_agent"]
    selected = re.search(r"^selected step (\d+) \(held-out weighted residual (-?[0-9.]+)\)", text, re.MULTILINE)
    assert selected and int(selected.group(1)) in (150, 300), text
    data = re.search(r"^expert data (-?[0-9.]+)\s+behaviour data (-?[0-9.]+)", text, re.MULTILINE)
    assert data and float(data.group(1)) > float(data.group(2)) + 300, text
    assert -4000 < _figure(text, "WBRM agent", "return") <= 0  # Pendulum's returns lie in [−16.3 · 200, 0]


def test_the_docs_show_the_whole_reuse_script():
    """The tutorial's reuse script is examples/wbrm_ddpg_lqr.py itself, in full (included from the file; the run above
    runs it), and the README points to it."""
    page = (ROOT / "docs" / "tutorials" / "torchrl_agent.md").read_text()
    assert "```{literalinclude} ../../examples/wbrm_ddpg_lqr.py\n" in page, "the tutorial lacks the example's source"
    assert "examples/wbrm_ddpg_lqr.py" in (ROOT / "README.md").read_text()


def test_every_example_is_tested():
    assert sorted(p.stem for p in (ROOT / "examples").glob("*.py")) == sorted(EXAMPLES)


def test_examples_use_only_public_api():
    """No private names of this package (``torchrl_wbrm.x._y`` or ``from torchrl_wbrm... import _y``)."""
    for path in (ROOT / "examples").glob("*.py"):
        text = path.read_text()
        assert not re.search(r"torchrl_wbrm[\w.]*\._\w", text), path
        assert not re.search(r"from torchrl_wbrm[\w.]* import [^\n]*\b_\w", text), path
        imports = re.findall(r"^from (torchrl_wbrm[\w.]*) import", text, re.MULTILINE)
        assert imports and all(m.count(".") == 1 for m in imports), (path, imports)  # package-level names


@pytest.mark.slow
def test_the_docs_show_what_the_example_prints(outputs):
    """The tutorial's output block of examples/wbrm_ddpg_lqr.py is what the quick run printed: the same lines, each
    figure within 0.003 (another CPU may round the last digits of a float computation differently)."""
    readme = (ROOT / "docs" / "tutorials" / "torchrl_agent.md").read_text()
    shown = re.search(r"<!-- example-output: wbrm_ddpg_lqr -->\n```\n(.*?)```\n<!-- /example-output -->", readme,
                      re.DOTALL)
    assert shown, "the tutorial lacks the example-output block"
    number = r"-?\d+\.\d+"
    expected, got = shown.group(1).strip().splitlines(), outputs["wbrm_ddpg_lqr"].strip().splitlines()
    assert len(expected) == len(got), (expected, got)
    for want, have in zip(expected, got):
        assert re.sub(number, "#", want) == re.sub(number, "#", have), (want, have)
        for a, b in zip(re.findall(number, want), re.findall(number, have)):
            assert abs(float(a) - float(b)) <= 3e-3, (want, have)

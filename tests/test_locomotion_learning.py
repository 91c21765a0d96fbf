"""Learning tests on small locomotion datasets made in the test by :func:`torchrl_wbrm.data.locomotion.
make_locomotion_task` from each committed expert, in the regime where uniform sampling is known to collapse.

The data, per task: an expert pool of 8 noisy-expert episodes and ``random-expert05-v0`` at 50,000 transitions
(uniform random actions, 5% of the transitions from whole noisy-expert episodes spread among the random ones; no
``medium-v0``). The run: the recipe's defaults with only the dataset keys (``S^e`` is 5 episodes of the pool, drawn
by the run's seed) and a stage-2 budget of 300 updates. The bar comes from the data's own returns: the behaviour
data's mean episode return plus half the gap to the expert pool's mean return.

- Hopper (bar 565: behaviour 21.5, pool 1108.3): the default recipe, measured (seed: final return over 5 episodes,
  no flag on any) 0: 1030, 1: 1056, 2: 965. With ``q.steps=10`` (the actor all but untrained) it returns 290 and
  fails. On a 20,000-transition ``D`` holding only 3 expert episodes, seed 1's ŵ averaged 0.06 over ``D`` and the
  run was flagged ``ratio_collapse``.
- HalfCheetah (bar 2432: behaviour 10.6 over 50 episodes, 3 of them the expert's; pool 4852.4): the default recipe
  FAILS, an expected failure kept as a strict ``xfail`` so that a fix shows: stage 1 collapses (the mean of ŵ over
  ``D`` is 85.5, 91% of ``D``'s rows at ŵ's lower bound) and stage 2 on those weights returns 544 at 300 updates
  and −93 at 1,000. The same run with ŵ ≡ 1 (``algo=brm``) passes at seed 0 (2786) but not at every seed: seed 1
  returns 1340 and seed 2 −576 (flagged ``below_behaviour``). At 300 updates stage 2 on HalfCheetah is not reliable
  with or without the ratio; the test holds the seed-0 run.
- Walker2d (bar 1026: behaviour 6.8 over 2,202 episodes, 6 of them the expert's; pool 2045.4, an expert that falls
  in some episodes): the default recipe FAILS (strict ``xfail``): seeds 0, 1, 2 return −23 (flagged
  ``below_behaviour``; ŵ averages 0.15 over ``D``, 98% of its rows at the lower bound), 102 and 388. Nothing else
  passes either: ŵ ≡ 1 returns 124 at 300 updates and −42 at 3,000, cloning ``S^e`` 476, and the untrained actor
  (``q.steps=10``) 263.
"""
from __future__ import annotations

import importlib.util
import json

import pytest

pytestmark = [pytest.mark.skipif(importlib.util.find_spec("mujoco") is None, reason="needs mujoco"),
              pytest.mark.slow]

TRANSITIONS = 50_000
EXPERT_SHARE = 5  # percent of D's transitions
POOL_EPISODES = 8
DEMONSTRATIONS = 5
#: stage 2's budget per task (updates)
STEPS = {"hopper": 300, "halfcheetah": 300, "walker2d": 300}
#: the bar: the behaviour data's mean episode return plus this fraction of the gap to the expert pool's
FRACTION_OF_THE_GAP = 0.5


def _committed_tasks() -> list[str]:
    """The locomotion tasks whose expert and medium policies are committed (each gets the tests below)."""
    from torchrl_wbrm.policies.locomotion import EXPERTS_DIR

    return sorted({p.stem.rsplit("-", 1)[0] for p in EXPERTS_DIR.glob("*-expert.pt")})


#: (task, algo) of the learning test: the default recipe (``wbrm``) on every task, and where it fails, the same with
#: ŵ ≡ 1 (``brm``) beside it, so that the data and stage 2 are shown to learn without the ratio
LEARNING_CASES = [
    ("hopper", "wbrm"),
    pytest.param("halfcheetah", "wbrm", marks=pytest.mark.xfail(strict=True, reason=(
        "stage 1 collapses on HalfCheetah's mixture (flag ratio_collapse: the mean of ŵ over D is 85.5, 91% of "
        "D's rows at ŵ's lower bound), and stage 2 on those weights returns 544 at 300 updates"))),
    ("halfcheetah", "brm"),
    pytest.param("walker2d", "wbrm", marks=pytest.mark.xfail(strict=True, reason=(
        "on Walker2d's mixture no run reaches the bar at this budget: WBRM returns -23, 102 and 388 (seeds 0-2), "
        "BRM 124, cloning S^e 476"))),
]


@pytest.fixture(scope="module", params=_committed_tasks())
def task_data(request, tmp_path_factory):
    from torchrl_wbrm.data.locomotion import make_locomotion_task

    path = tmp_path_factory.mktemp(f"{request.param}_data")
    row = make_locomotion_task(request.param, path, transitions=TRANSITIONS, expert_shares=(EXPERT_SHARE,),
                               pool_episodes=POOL_EPISODES, medium=False, log=lambda line: None)
    made = {d["id"]: d for d in row["datasets"]}
    return path, row, made[row["expert_pool"]], made[row[f"random_expert{EXPERT_SHARE:02d}"]]


def test_the_small_mixture_holds_the_expert_share_it_was_asked_for(task_data):
    path, row, pool, mixture = task_data
    assert "medium" not in row and not (path / "benchmark" / row["task"] / "medium-v0").exists()
    assert pool["episodes"] == pool["expert_episodes"] == POOL_EPISODES
    # at least 5% of the transitions, less than one more expert episode above it, and not 5% of the episodes
    import gymnasium as gym

    longest = gym.spec(row["env_id"]).max_episode_steps
    assert TRANSITIONS <= mixture["transitions"] < TRANSITIONS + longest
    assert EXPERT_SHARE / 100 <= mixture["expert_transitions"] / mixture["transitions"]
    assert mixture["expert_transitions"] - longest < EXPERT_SHARE / 100 * TRANSITIONS
    random_length = (mixture["transitions"] - mixture["expert_transitions"]) / (
        mixture["episodes"] - mixture["expert_episodes"])
    if random_length < mixture["expert_transitions"] / mixture["expert_episodes"] / 5:  # short random episodes
        assert mixture["expert_episodes"] / mixture["episodes"] < EXPERT_SHARE / 100 / 5
    meta = json.loads(next((path / row[f"random_expert{EXPERT_SHARE:02d}"]).rglob("metadata.json")).read_text())
    assert len(meta["expert_episode_ids"]) == mixture["expert_episodes"] > 1
    # the gap the bar is set in: the random episodes return little, the expert far more
    assert mixture["return_mean"] < pool["return_mean"] / 10


@pytest.mark.parametrize("task_data,algo", [case for case in LEARNING_CASES
                                             if (case.values if hasattr(case, "values") else case)[0]
                                             in _committed_tasks()], indirect=["task_data"])
def test_the_defaults_learn_from_five_demonstrations_among_random_data(task_data, algo, tmp_path):
    from torchrl_wbrm.data.minari_data import MinariDataConfig
    from torchrl_wbrm.tasks import EnvConfig
    from torchrl_wbrm.training import WBRMConfig, WBRMTrainer

    path, row, pool, mixture = task_data
    minari = MinariDataConfig(expert=row["expert_pool"], behaviour=row[f"random_expert{EXPERT_SHARE:02d}"],
                              data_path=str(path), expert_episodes=DEMONSTRATIONS)
    cfg = WBRMConfig(env=EnvConfig(name="minari", kind="minari", minari=minari), plots=False, threads=1, seed=0,
                     algo=algo)
    cfg.q.steps = cfg.q.eval_every = STEPS[row["task"]]
    cfg.eval.episodes = 5
    res = WBRMTrainer(cfg, tmp_path / "run", progress=False).run()
    assert res["status"] == "finished" and res["flags"] == [], (res["status"], res["flags"])
    assert len(res["data"]["expert_episode_ids"]) == DEMONSTRATIONS, res["data"]
    final = res["final"]
    # the run read the data the test made: its behaviour return is the make-up's
    assert final["data_behaviour_mean_return"] == pytest.approx(mixture["return_mean"], rel=1e-5)
    behaviour, expert = mixture["return_mean"], pool["return_mean"]
    bar = behaviour + FRACTION_OF_THE_GAP * (expert - behaviour)
    assert final["return"] > bar, (final["return"], bar, behaviour, expert)
    assert "normalised_score" in final  # D4RL's scale, from the references the datasets record

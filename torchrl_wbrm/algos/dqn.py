"""DQN (V. Mnih et al., "Human-level control through deep reinforcement learning", Nature 2015), offline, on the
discretised action box."""
from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.objectives import DQNLoss, SoftUpdate

from torchrl_wbrm.algos.base import Algo, AlgoContext, adam, critic_options, descend
from torchrl_wbrm.algos.registry import register_algo
from torchrl_wbrm.modules import make_discrete_q_network


@dataclass
class DQNConfig:
    """DQN with torchrl's ``DQNLoss`` on a discretised action box (``baselines.dqn``).

    Attributes:
        num_bins: values per action coordinate (the env's ``ActionDiscretizer`` grid, bin medians), at least 2; one
            categorical over the ``num_bins ** m`` joint actions (LQR: ``num_bins ** 2``; MountainCar: ``num_bins``).
        loss_function: the TD loss.
    """

    num_bins: int = 21
    loss_function: str = "l2"


def _check(settings: DQNConfig, key: str) -> None:
    if not settings.num_bins >= 2:
        raise ValueError(f"{key}.num_bins must be >= 2, got {settings.num_bins}.")


@register_algo("dqn", config=DQNConfig, validate=_check, loss="torchrl `DQNLoss` on the discretised action box",
               reference="Mnih et al. 2015", loss_title="DQN: TD loss")
def build_dqn(ctx: AlgoContext) -> Algo:
    """torchrl's ``DQNLoss`` on a Q head over the ``num_bins ** m`` joint actions of the env's
    :class:`~torchrl_wbrm.modules.ActionGrid` (categorical indices; ``ctx.task.action_grid``). The dataset's
    continuous actions are snapped to the nearest grid point once, before they enter the buffer; the evaluated policy
    is the greedy head followed by a module mapping its index back to the continuous action, so it runs in the
    continuous env against the same optimum. Targets by ``SoftUpdate``. The Q* error is scored at the grid point
    nearest to each evaluation action.
    """
    qc, dc = ctx.cfg.q, ctx.cfg.baselines.dqn
    if ctx.task is None:
        raise ValueError("algo=dqn needs the env's task (AlgoContext.task) for its action grid.")
    grid = ctx.task.action_grid(dc.num_bins).to(ctx.device)
    q_head = make_discrete_q_network(ctx.observation_dim, grid.num_actions, action_space="categorical",
                                     **critic_options(ctx)).to(ctx.device)
    loss = DQNLoss(q_head, loss_function=dc.loss_function, delay_value=True)
    loss.make_value_estimator(gamma=ctx.gamma)
    updater = SoftUpdate(loss, tau=qc.target_tau)
    optimisers = {"value": adam(loss.value_network_params.values(True, True), qc.lr)}
    policy = TensorDictSequential(q_head, TensorDictModule(grid, in_keys=["action"], out_keys=["action"]))

    def step(batch: TensorDictBase, i: int) -> dict:
        out = loss(batch)
        descend(out["loss"], optimisers["value"], qc.grad_clip)
        updater.step()
        return {"loss_value": out["loss"].detach()}

    def map_data(td: TensorDictBase) -> TensorDictBase:
        td = td.clone()
        td.set("continuous_action", td["action"])
        td.del_("action")
        td.set("action", grid.index(td["continuous_action"]))
        return td

    def q_value(td: TensorDictBase):
        index = grid.index(td["action"])
        with loss.value_network_params.to_module(loss.value_network):
            values = loss.value_network(td.select("observation").clone())["action_value"]
        return values.gather(-1, index.unsqueeze(-1)).reshape(-1), grid(index)

    return Algo(loss=loss, optimisers=optimisers, step=step, policy=policy, q_value=q_value, map_data=map_data)

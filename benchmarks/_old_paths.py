"""A context manager that turns every speed shortcut of the project off, for same-process comparisons: the
TensorDict/``to_module`` loss paths, torchrl's ``SoftUpdate``, the replay buffers' own ``sample()``, torchrl's
``EnvBase.rollout`` and (``fused=False``) the for-loop Adam."""
from __future__ import annotations

from contextlib import ExitStack, contextmanager
from unittest import mock


class _Plain:
    """The replay buffer's own ``sample()``, moved to the device (what the trainer did before ``BufferBatches``)."""

    def __init__(self, sampler, device):
        self.sampler, self.device = sampler, device

    def sample(self):
        return self.sampler.sample().to(self.device)


@contextmanager
def old_paths(*, shortcuts: bool = False, fused: bool = False):
    from torchrl.envs import EnvBase
    from torchrl.objectives import SoftUpdate

    from torchrl_wbrm.data.datasets import PairedSampler
    from torchrl_wbrm.envs import LQREnv
    from torchrl_wbrm.objectives import RobustDensityRatioLoss, WeightedBellmanLoss
    from torchrl_wbrm.training import algos, trainer as trainer_module

    # the algorithms' builders: training.algos, or (issue 13's layout) torchrl_wbrm.algos.base, which
    # training.algos re-exports; each name is patched where the builders look it up
    builders = [algos]
    try:
        from torchrl_wbrm.algos import base as algos_base
    except ImportError:
        algos_base = None
    if algos_base is not None:
        builders.append(algos_base)

    def patch_all(name, value):
        for module in builders:
            if hasattr(module, name):
                stack.enter_context(mock.patch.object(module, name, value))

    with ExitStack() as stack:
        if not fused:
            patch_all("adam_options", lambda params: {})
            stack.enter_context(mock.patch.object(trainer_module, "adam_options", lambda params: {}))
        if not shortcuts:
            stack.enter_context(mock.patch.object(WeightedBellmanLoss, "fast_path", False))
            stack.enter_context(mock.patch.object(RobustDensityRatioLoss, "fast_path", False))
            patch_all("ForeachSoftUpdate", SoftUpdate)
            stack.enter_context(mock.patch.object(LQREnv, "rollout", EnvBase.rollout))
            stack.enter_context(mock.patch.object(
                trainer_module, "PairedBatches", lambda b, e, n, device=None: _Plain(PairedSampler(b, e, n), device)))
            stack.enter_context(mock.patch.object(trainer_module.WBRMTrainer, "_q_batches",
                                                  lambda self: _Plain(self.q_buffer, self.device)))
        yield

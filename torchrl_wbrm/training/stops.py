"""What stops a run: a non-finite figure or parameter (:class:`TrainingDiverged`), and SIGINT or SIGTERM
(:class:`StopSignals`), which end the run at the next step boundary, after a checkpoint (:class:`RunInterrupted`).
"""
from __future__ import annotations

import contextlib
import math
import signal
import threading
import warnings
from pathlib import Path

import torch

from torchrl_wbrm.keys import CHECKPOINT

__all__ = ["RECIPE_COMMAND", "FiniteWatch", "QBound", "RunInterrupted", "resume_command", "StopNow", "StopSignals",
           "TrainingDiverged", "first_non_finite", "non_finite_parameter"]


class TrainingDiverged(RuntimeError):
    """A non-finite figure or parameter stopped the run; ``stage``, ``step``, ``figure`` and ``value`` say where."""

    def __init__(self, stage: str, step: int, figure: str, value: float, checkpoint_step: int | None = None):
        self.stage, self.step, self.figure, self.value = stage, step, figure, value
        self.checkpoint_step = checkpoint_step
        super().__init__(
            f"Training diverged in stage {stage!r} at step {step}: {figure} = {value}. The run stopped; the last "
            f"checkpoint with finite values is kept."
        )


#: the recipe's command, as the resume hint names it unless told how the recipe was started
RECIPE_COMMAND = "python recipes/wbrm_offline.py"


def resume_command(run_dir, command: str = RECIPE_COMMAND) -> str:
    """The command that resumes the run in ``run_dir``, as a shell reads it: ``command`` (how the recipe was
    started, :func:`torchrl_wbrm.cli.recipe_command`) and ``resume=<run dir>``, the override quoted
    (``shlex.quote``) where the path holds a space or another character a shell would split on."""
    import shlex

    return f"{command} {shlex.quote(f'resume={run_dir}')}"


class RunInterrupted(Exception):
    """SIGINT or SIGTERM stopped the run after a checkpoint; ``signal_name``, ``stage``, ``step``, ``run_dir``."""

    def __init__(self, signum: int, stage: str, step: int, run_dir: Path, *, during: str | None = None,
                 command: str = RECIPE_COMMAND):
        self.signum, self.stage, self.step, self.run_dir = signum, stage, step, Path(run_dir)
        self.signal_name = signal.Signals(signum).name
        self.during = during
        where = f"during the {during} " if during else ""
        super().__init__(
            f"{self.signal_name} received: stopped {where}in stage {stage!r} at step {step}, checkpoint written to "
            f"{self.run_dir / CHECKPOINT}. Resume with: {resume_command(self.run_dir, command)}"
        )

    def with_command(self, command: str) -> "RunInterrupted":
        """The same stop, its resume hint naming ``command`` (how the recipe was started)."""
        return RunInterrupted(self.signum, self.stage, self.step, self.run_dir, during=self.during, command=command)

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


class StopNow(Exception):
    """A signal interrupted a :meth:`StopSignals.immediately` block; ``signum`` is the signal."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f"{signal.Signals(signum).name} received")


class StopSignals:
    """A context manager that turns SIGINT/SIGTERM into a flag (``.received``: the signal number or ``None``).

    The trainer polls it at step boundaries, writes a checkpoint and raises :class:`RunInterrupted`. A second signal
    while the flag is set falls back to the previous handler (so a stuck run can still be killed). Off the main
    thread (where Python cannot install handlers) it does nothing.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict = {}
        self._immediate = False

    def _handle(self, signum, frame) -> None:
        if self.received is not None:  # a second signal: the previous behaviour (KeyboardInterrupt, or exit)
            previous = self._previous.get(signum)
            if callable(previous):
                previous(signum, frame)
            else:
                raise KeyboardInterrupt
            return
        self.received = signum
        if self._immediate:  # inside immediately(): stop now, not at the next step boundary
            self._immediate = False
            raise StopNow(signum)

    @contextlib.contextmanager
    def immediately(self):
        """A block a signal interrupts at once (:class:`StopNow`), for work that can be abandoned and redone, such as
        an evaluation (it changes no training state): a long evaluation stops promptly instead of looking hung. A
        signal received before the block raises at its start."""
        if self.received is not None:
            raise StopNow(self.received)
        self._immediate = True
        try:
            yield
        finally:
            self._immediate = False

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self._previous[sig] = signal.getsignal(sig)
                signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous if previous is not None else signal.SIG_DFL)
        self._previous = {}


def first_non_finite(figures: dict) -> tuple[str, float] | None:
    """The first ``(name, value)`` among scalar tensors/floats of ``figures`` that is NaN or ±inf.

    CPU scalars are read one by one (``.item()``: no device to wait for, and cheaper than stacking them); where one
    of them lives on an accelerator, they are all stacked in float64 and read in one host sync."""
    scalars = [(name, value) for name, value in figures.items()
               if (isinstance(value, torch.Tensor) and value.numel() == 1)
               or (isinstance(value, (int, float)) and not isinstance(value, bool))]
    if not any(isinstance(v, torch.Tensor) and (v.device.type != "cpu" or v.is_complex()) for _, v in scalars):
        for name, value in scalars:
            value = value.item() if isinstance(value, torch.Tensor) else value
            if not math.isfinite(value):
                return name, float(value)
        return None
    stacked = torch.stack([value.detach().reshape(()).to(torch.float64).cpu() if isinstance(value, torch.Tensor)
                           else torch.tensor(float(value), dtype=torch.float64) for _, value in scalars])
    finite = torch.isfinite(stacked)
    if bool(finite.all()):
        return None
    i = int((~finite).nonzero()[0])
    return scalars[i][0], float(stacked[i])


class FiniteWatch:
    """The divergence check of a stage's step figures on ``device``: :func:`first_non_finite` on CPU (a host read
    costs nothing there). On an accelerator a device-side "all finite so far" flag is accumulated without a host sync
    and read (one sync) only when ``read`` (log, evaluation and checkpoint steps, the last step, a stop signal), so a
    divergence is caught at the next such step, before anything after it is logged or checkpointed; it names that
    step's first non-finite figure (a NaN persists), or the window's if they are finite again."""

    def __init__(self, device) -> None:
        self.device, self.flag = torch.device(device), None

    def __call__(self, figures: dict, *, read: bool) -> tuple[str, float] | None:
        if self.device.type == "cpu":
            return first_non_finite(figures)
        values = [v.detach().reshape(()).float() for v in figures.values()
                  if isinstance(v, torch.Tensor) and v.numel() == 1 and (v.is_floating_point() or v.is_complex())]
        if values:
            ok = torch.isfinite(torch.stack(values)).all()
            self.flag = ok if self.flag is None else self.flag & ok
        if not read or self.flag is None:
            return None
        flag, self.flag = self.flag, None
        if bool(flag):
            return None
        return first_non_finite(figures) or ("a figure of the steps since the last check", float("nan"))


def non_finite_parameter(*modules) -> str | None:
    """The name of the first parameter or buffer with a non-finite entry in ``modules``, or ``None``."""
    for module in modules:
        if module is None:
            continue
        for name, tensor in (*module.named_parameters(), *module.named_buffers()):
            if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
                return name
    return None


class QBound:
    """Q past ``factor · max|r| / (1 − γ)`` has blown up: no discounted return of rewards bounded by max|r| is that
    large (:func:`~torchrl_wbrm.objectives.functional.q_value_bound`). The one rule of a run's Q scale: the trainer
    warns once when a logged training figure of Q passes it (:meth:`watch`), and flags ``q_blow_up`` in the results
    when a figure of the delivered Q does (:meth:`exceeded`).

    Args:
        reward_max: max|r| over the data.
        gamma: the discount.
        factor: the margin over the exact bound (:attr:`FACTOR`).
    """

    #: the margin over max|r| / (1 − γ)
    FACTOR = 10.0
    #: the training figures of Q the watch reads
    FIGURES = ("q_mean", "target_value_mean", "actor_q_mean")

    def __init__(self, reward_max: float, gamma: float, factor: float = FACTOR):
        from torchrl_wbrm.objectives.functional import q_value_bound

        self.reward_max, self.gamma, self.factor = float(reward_max), float(gamma), float(factor)
        self.bound = q_value_bound(self.reward_max, self.gamma)  # the exact bound
        self.limit = q_value_bound(self.reward_max, self.gamma, self.factor)
        self.warned = False

    def exceeded(self, value: float | None) -> bool:
        """Whether ``|value|`` is past the limit."""
        return value is not None and abs(value) > self.limit

    def watch(self, figures: dict[str, float], step: int) -> None:
        """Warn once (a ``UserWarning``) when a figure of :attr:`FIGURES` is past the limit, naming it and the likely
        causes."""
        if self.warned:
            return
        for name in self.FIGURES:
            value = figures.get(name)
            if isinstance(value, float) and math.isfinite(value) and self.exceeded(value):
                self.warned = True
                warnings.warn(
                    f"|{name}| reached {abs(value):.4g} at step {step}, past {self.factor:g} · max|r| / (1 − γ) = "
                    f"{self.limit:.4g} (max|r| = {self.reward_max:.4g}, γ = {self.gamma:g}), larger than any "
                    "discounted return of these rewards: Q is diverging. Likely cause: Q started far from its targets "
                    "(q.init_bias); else a learning rate too high for the bootstrap, or a target updated too fast "
                    "(a smaller q.target_tau). This warning is given once per run.", UserWarning, stacklevel=2)
                return

"""One run's parts, built from its prepared config in the order a run draws its random numbers: D, S^b, S^e and D's
split (:func:`load_run_data`), stage 1's fitter (:func:`make_ratio_fitter`), stage 2's algo and its learning-rate
schedules (:func:`make_algo`), and the refusal of a setting these parts cannot carry out (:func:`check_d_settings`).
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from torchrl_wbrm.data import OfflineDatasets
from torchrl_wbrm.data.datasets import split_by_episode
from torchrl_wbrm.keys import EPISODE
from torchrl_wbrm.modules import DensityRatioNetwork
from torchrl_wbrm.objectives import RobustDensityRatioLoss
from torchrl_wbrm.ratio import DensityRatioFitter
from torchrl_wbrm.algos import Algo, AlgoContext, adam_options, build_algo, get_algo
from torchrl_wbrm.tasks import cached_offline_datasets
from torchrl_wbrm.training.checkpoint import data_fingerprint
from torchrl_wbrm.training.selection import EXPERT_LIKE
from torchrl_wbrm.training.stops import QBound

__all__ = ["RunData", "check_d_settings", "load_run_data", "make_algo", "make_ratio_fitter", "step_schedulers"]


@dataclass
class RunData:
    """One run's data, D's split and the figures its task and D set (:func:`load_run_data`)."""

    datasets: OfflineDatasets  # D, S^b and S^e
    train: TensorDictBase  # D's training episodes (stage 2's rows)
    holdout: TensorDictBase  # D's held-out episodes (q.holdout_fraction of them, drawn with seed + 23)
    action_spec: object  # the task's
    gamma: float  # the task's γ for q.gamma
    q_bound: QBound  # Q's scale, from D's largest |reward| and γ
    fingerprint: str  # the SHA-256 of every tensor of D, S^b and S^e: a resume on other data is refused
    seconds: float  # making or reading the data, the task's checks' read of them included


def load_run_data(cfg, task) -> RunData:
    """The run's data: made by ``task`` (or read from ``cfg.data_cache``), attached to it, D split by episode."""
    t0 = time.perf_counter()
    if cfg.data_cache:
        datasets = cached_offline_datasets(cfg.env, seed=cfg.seed, cache_dir=cfg.data_cache)
    else:
        datasets = task.make_datasets(seed=cfg.seed)
    task.attach(datasets)
    seconds = time.perf_counter() - t0 + task.check_seconds
    d = datasets.transitions[:]
    train, holdout = split_by_episode(d, cfg.q.holdout_fraction, generator=torch.Generator().manual_seed(cfg.seed + 23))
    action_spec = task.action_spec()
    gamma = task.gamma(cfg.q.gamma)
    return RunData(datasets, train, holdout, action_spec, gamma, QBound(float(d["next", "reward"].abs().max()), gamma),
                   data_fingerprint(datasets), seconds)


def make_ratio_fitter(cfg, data: RunData, device) -> DensityRatioFitter | None:
    """Stage 1: :mod:`torchrl_wbrm.ratio`'s fitter of the ``ratio`` settings on S^b and S^e (held-out split drawn with
    ``seed + 17``); ``None`` where the run fits no ratio (``ratio.source`` not ``learned``, or an algo reading none)."""
    rc = cfg.ratio
    if rc.source != "learned" or not get_algo(cfg.algo).fits_ratio_for(cfg):
        return None
    d = data.train
    network = DensityRatioNetwork(d["observation"].shape[-1], d["action"].shape[-1], bounds=tuple(rc.bounds),
                                  parameterisation=rc.parameterisation, num_cells=rc.num_cells,
                                  activation=rc.activation, layer_norm=rc.layer_norm).to(device)
    loss = RobustDensityRatioLoss(network, alpha="kl" if rc.divergence == "kl" else rc.alpha,
                                  normalisation_coefficient=rc.normalisation_coefficient,
                                  non_negative_correction=rc.non_negative_correction, relative_beta=rc.relative_beta)
    params = list(loss.parameters())
    optimiser = torch.optim.Adam(params, lr=rc.lr, weight_decay=rc.weight_decay, **adam_options(params))
    return DensityRatioFitter(
        loss, data.datasets.behaviour_samples, data.datasets.expert_samples, batch_size=rc.batch_size,
        optimizer=optimiser, grad_clip=rc.grad_clip, holdout_fraction=rc.holdout_fraction,
        generator=torch.Generator().manual_seed(cfg.seed + 17), patience=rc.patience, device=device)


def make_algo(cfg, task, data: RunData, device) -> tuple[Algo, dict]:
    """Stage 2 (or the baseline named by ``algo``): the algo (loss, optimisers, step function, evaluated policy) and
    its learning-rate schedules (``q.lr_schedule=cosine``: every optimiser annealed over ``q.steps``)."""
    qc = cfg.q
    d = data.datasets.transitions[:]
    init_bias = d["next", "reward"].mean().item() / (1 - data.gamma) if qc.init_bias else 0.0
    loc = scale = None
    if qc.normalise_observations:  # D's statistics, a fixed input layer of every network
        observations = data.train["observation"].double()
        loc, scale = observations.mean(0).float(), observations.std(0).clamp_min(1e-6).float()
    algo = build_algo(cfg.algo, AlgoContext(
        cfg=cfg, observation_dim=d["observation"].shape[-1], action_dim=d["action"].shape[-1],
        action_spec=data.action_spec, gamma=data.gamma, q_initial_bias=init_bias, device=device,
        observation_loc=loc, observation_scale=scale, task=task))
    schedulers = {}
    if qc.lr_schedule == "cosine":  # stepped once per trainer step (step_schedulers)
        schedulers = {name: torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=qc.steps)
                      for name, optimiser in algo.optimisers.items()}
    return algo, schedulers


def step_schedulers(schedulers: dict) -> None:
    """One step of each learning-rate schedule in ``schedulers`` (an actor updated every k-th step has not stepped
    its optimiser yet at step 1: torch's warning about that order is expected and silenced)."""
    if not schedulers:
        return
    if all(scheduler.last_epoch > 0 for scheduler in schedulers.values()):  # each stepped once already
        for scheduler in schedulers.values():  # torch warns only on a schedule's first step: no filter to set up
            scheduler.step()
        return
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Detected call of `lr_scheduler\.step\(\)` before")
        for scheduler in schedulers.values():
            scheduler.step()


def check_d_settings(cfg, algo: Algo, train: TensorDictBase) -> None:
    """Refuse, in one line and before stage 1, a setting the run cannot carry out after it: ``q.select`` by the
    held-out Bellman residual for an algo without one, ``q.expert_bc_from_d`` for an algo without the S^e cloning
    term, and, on data without episode ids (key ``"episode"``), a setting that reads D's episodes:
    ``q.expert_bc_from_d``, an algo that marks D's expert-like episodes, ``ratio.aggregate='episode'`` where the algo
    reads a ratio, and a ``q.select`` on D's expert-like episodes."""
    qc = cfg.q
    if qc.select != "last" and algo.bellman_loss is None:
        raise ValueError(f"q.select={qc.select} chooses by the held-out Bellman residual, which algo={cfg.algo} does "
                         f"not fit: use q.select=last or an algo with one (wbrm, brm, fqi, mabo).")
    if qc.expert_bc_from_d and algo.cloning is None:  # validate_config refuses it for the built-in algos without
        # the S^e cloning term; a custom algo may lack one
        raise ValueError(f"q.expert_bc_from_d=true extends the actor's S^e cloning term, which algo={cfg.algo} "
                         f"does not have.")
    if EPISODE in train.keys():
        return
    reads_ratio = algo.uses_ratio and cfg.ratio.source != "none"
    for needed, setting, instead in (
            (qc.expert_bc_from_d, "q.expert_bc_from_d=true", "set q.expert_bc_from_d=false"),
            (algo.marks_expert_like, f"algo={cfg.algo}'s cloning of D's expert-like episodes",
             "choose another of its settings"),
            (reads_ratio and cfg.ratio.aggregate == "episode", "ratio.aggregate='episode'",
             "use ratio.aggregate=transition"),
            (qc.select in EXPERT_LIKE, f"q.select={qc.select}", "use q.select=held_out_weighted_residual")):
        if needed:
            raise ValueError(f"{setting} needs D's episode ids (key 'episode'), which these data do not hold: "
                             f"{instead}.")

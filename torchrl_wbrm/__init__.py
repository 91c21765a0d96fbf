"""torchrl_wbrm: TorchRL components for Deep Weighted Bellman Residual Minimization (WBRM).

Layers, lowest first (a layer imports only from layers below it):
``envs`` → ``policies``, ``modules``, ``evaluation`` → ``data`` (with ``data.tasks``: one task object per env kind) →
``objectives`` → ``ratio`` (stage 1 as a library: fit ŵ, compute it over a dataset, shape and store it) → ``algos``
(one file per algorithm, registered) → ``training``.
"""

__version__ = "0.1.0"

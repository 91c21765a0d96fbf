"""torchrl_wbrm: TorchRL components for Deep Weighted Bellman Residual Minimization (WBRM).

Layers, lowest first (a layer imports only from layers below it):
``envs`` → ``policies`` → ``data`` → ``modules`` → ``objectives`` → ``evaluation`` → ``ratio`` (stage 1 as a library:
fit ŵ, compute it over a dataset, shape and store it) → ``training``.
"""

__version__ = "0.1.0"

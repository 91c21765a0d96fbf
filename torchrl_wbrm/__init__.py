"""torchrl_wbrm: TorchRL components for Deep Weighted Bellman Residual Minimization (WBRM).

Layers, lowest first (a layer imports only from layers below it):
``envs`` → ``policies``, ``modules``, ``evaluation`` → ``data`` (reading and writing datasets) → ``tasks`` (one task
object per env kind, with its training defaults) → ``objectives`` → ``ratio`` (stage 1 as a library: fit ŵ, compute it over a dataset, shape and store it) → ``algos``
(one file per algorithm, registered) → ``training``.
"""

from torchrl_wbrm._console import quiet_libraries

__version__ = "0.1.0"

quiet_libraries()  # no library [INFO] lines on the console by default (TORCHRL_WBRM_VERBOSE=1 keeps them)

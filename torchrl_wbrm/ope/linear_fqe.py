r"""Q linear in fixed features, fitted by least-squares FQE or FQI, and the greedy policy of a Q quadratic in a.

Least-squares FQE is :class:`~torchrl_wbrm.objectives.FQELoss` with its inner minimisation solved exactly: each
iteration reads the loss's targets ``Y_i = r_i + γ (1 − terminated_i) Q_{θ_k}(x'_i, π(x'_i))`` (its
:meth:`~torchrl_wbrm.objectives.FQELoss.bellman_error`, target parameters ``θ_k``), solves the weighted least squares

.. math::

    \theta_{k+1} = \arg\min_\theta \sum_i w_i \left(\phi(x_i, a_i)^\top \theta - Y_i\right)^2 + \lambda \|\theta\|^2

(the minimiser of the loss's ``Σ wᵢ ℓᵢ / Σ wᵢ`` over the whole of D), and copies ``θ_{k+1}`` into the target (a hard
update). With π the greedy policy of the target Q (:class:`GreedyQuadraticPolicy`, updated with it) the same
iteration is fitted Q iteration for Q*. With the features of
:class:`~torchrl_wbrm.modules.PolynomialFeatures` of degree 2 the class holds every quadratic, hence the Q* and
``Q^π`` of an LQR with the *unclipped* reward; the environment's clip at 0 makes them non-quadratic where the cost
passes the reward's offset (far from 0), so the class cannot fit them everywhere. Degree 1 cannot fit them anywhere.
"""
from __future__ import annotations

import itertools

import torch
from tensordict import TensorDictBase
from torch import nn

from torchrl_wbrm.modules import PolynomialFeatures
from torchrl_wbrm.objectives import FQELoss

__all__ = ["GreedyQuadraticPolicy", "LinearQ", "least_squares_fqe"]


class LinearQ(nn.Module):
    """``Q(x, a) = φ(x, a)ᵀθ`` with ``φ`` the monomials of :class:`~torchrl_wbrm.modules.PolynomialFeatures` of
    ``degree``; θ (float64) starts at ``initial_value`` on the constant feature and 0 elsewhere.

    Examples:
        >>> import torch
        >>> q = LinearQ(2, 1, degree=1, initial_value=3.0)
        >>> q(torch.zeros(4, 2), torch.zeros(4, 1)).squeeze(-1).detach()
        tensor([3., 3., 3., 3.])
    """

    def __init__(self, observation_dim: int, action_dim: int, *, degree: int = 2, initial_value: float = 0.0):
        super().__init__()
        self.features = PolynomialFeatures(degree)
        theta = torch.zeros(self.features.num_features(observation_dim + action_dim), dtype=torch.float64)
        theta[0] = initial_value
        self.theta = nn.Parameter(theta)

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        phi = self.features(observation.to(torch.float64), action.to(torch.float64))
        return (phi @ self.theta).unsqueeze(-1).to(observation.dtype)


class GreedyQuadraticPolicy(nn.Module):
    """``argmax_{a ∈ [−b, b]^m} Q(x, a)`` for a :class:`LinearQ` ``Q`` (quadratic, or linear, in ``a``): the
    stationary point ``−H⁻¹ g(x)`` where the Hessian ``H`` in ``a`` is negative definite, clamped to the box, else
    the best corner of the box; of those candidates the one with the largest Q. For a Q quadratic in ``(x, a)``,
    ``H`` is constant and the gradient ``g(x) = g_0 + B x`` linear; both are read exactly from Q on a few probe points
    (finite differences are exact for a quadratic). Holds its own θ (copy the target's in with :meth:`set_theta` or
    through a loss's policy parameters)."""

    def __init__(self, q: LinearQ, action_dim: int, bound: float) -> None:
        super().__init__()
        self.q = q
        self.action_dim = int(action_dim)
        self.bound = float(bound)
        corners = torch.tensor(list(itertools.product((-1.0, 1.0), repeat=self.action_dim)), dtype=torch.float64)
        self.register_buffer("corners", corners * self.bound)

    def set_theta(self, theta: torch.Tensor) -> None:
        with torch.no_grad():
            self.q.theta.copy_(theta)

    def _q(self, x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return self.q(x, a).squeeze(-1)

    def _gradient_and_hessian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``g(x)`` (``[N, m]``) and ``H`` (``[m, m]``) at the probe states ``x`` (``[N, d]``)."""
        m = self.action_dim
        eye = torch.eye(m, dtype=torch.float64)

        def at(a):
            return self._q(x, a.expand(x.shape[0], m))

        q0 = at(torch.zeros(m, dtype=torch.float64))
        grad = torch.stack([(at(eye[k]) - at(-eye[k])) / 2 for k in range(m)], -1)
        hessian = torch.stack([torch.stack([at(eye[k] + eye[j]) - at(eye[k]) - at(eye[j]) + q0 for j in range(m)], -1)
                               for k in range(m)], -2)
        return grad, hessian[0]

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        x = observation.to(torch.float64).reshape(-1, observation.shape[-1])
        d, m = x.shape[-1], self.action_dim
        probes = torch.cat([torch.zeros(1, d, dtype=torch.float64), torch.eye(d, dtype=torch.float64)])
        grad, h = self._gradient_and_hessian(probes)
        g0, slope = grad[0], (grad[1:] - grad[0]).T  # g(x) = g0 + slope @ x
        candidates = [a.expand(x.shape[0], m) for a in self.corners]
        if bool((torch.linalg.eigvalsh(0.5 * (h + h.T)) < 0).all()):
            stationary = -torch.linalg.solve(h, (g0 + x @ slope.T).T).T
            candidates.append(stationary.clamp(-self.bound, self.bound))
        stacked = torch.stack(candidates, 0)
        values = torch.stack([self._q(x, c) for c in stacked], 0)
        best = values.argmax(0)
        action = stacked.gather(0, best.view(1, -1, 1).expand(1, x.shape[0], m)).squeeze(0)
        return action.reshape(*observation.shape[:-1], m).to(observation.dtype)


@torch.no_grad()
def least_squares_fqe(
    loss: FQELoss,
    data: TensorDictBase,
    features: PolynomialFeatures,
    *,
    weight: torch.Tensor | None = None,
    greedy: GreedyQuadraticPolicy | None = None,
    iterations: int = 300,
    tol: float = 1e-6,
    ridge: float = 1e-8,
) -> dict:
    """Least-squares FQE (or, with ``greedy``, FQI) of the :class:`LinearQ` in ``loss`` on all of ``data`` (see the
    module docstring); ``weight``: ``w_i ≥ 0`` per row (``None``: 1). ``greedy``: the policy module the loss was built
    with; its θ follows the target's (the loss's copy of π's parameters is updated). Stops when θ moves less than
    ``tol`` (max-abs, relative to its size) or after ``iterations``. Returns ``{"iterations", "converged",
    "residual"}`` (the last weighted mean δ²)."""
    if not loss.delay_value:
        raise ValueError("least_squares_fqe needs the loss's target parameters (delay_value=True).")
    phi = features(data.get("observation").to(torch.float64), data.get(loss.tensor_keys.action).to(torch.float64))
    w = torch.ones(phi.shape[0], dtype=torch.float64) if weight is None else weight.reshape(-1).to(torch.float64)
    if w.shape[0] != phi.shape[0] or not bool(torch.isfinite(w).all()) or bool((w < 0).any()):
        raise ValueError(f"weight must hold {phi.shape[0]} finite, non-negative values (one per row of data).")
    root = w.sqrt().unsqueeze(-1)
    gram = (root * phi).T @ (root * phi) + ridge * w.sum() * torch.eye(phi.shape[1], dtype=torch.float64)
    theta_key = [k for k in loss.value_network_params.keys(True, True) if k[-1] == "theta"][0]
    policy_theta = None
    if greedy is not None:
        policy_theta = [k for k in loss.policy_network_params.keys(True, True) if k[-1] == "theta"][0]
    converged, residual = False, float("nan")
    for iteration in range(1, iterations + 1):
        _, target = loss.bellman_error(data)
        rhs = (w.unsqueeze(-1) * phi).T @ target.to(torch.float64)
        theta = torch.linalg.solve(gram, rhs)
        old = loss.target_value_network_params.get(theta_key)
        step = (theta - old).abs().max() / theta.abs().max().clamp_min(1.0)
        loss.value_network_params.get(theta_key).data.copy_(theta)
        old.copy_(theta)
        if policy_theta is not None:
            loss.policy_network_params.get(policy_theta).data.copy_(theta)
        residual = float((w * (phi @ theta - target.to(torch.float64)).pow(2)).sum() / w.sum())
        if step < tol:
            converged = True
            break
    return {"iterations": iteration, "converged": converged, "residual": residual}

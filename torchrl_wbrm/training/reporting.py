"""Human-readable summaries of a run's results."""
from __future__ import annotations

__all__ = ["summarise"]


def summarise(results: dict) -> str:
    """A few lines: the final evaluation against the exact optimum (LQR) or the mean return (MountainCar)."""
    f = results.get("final", {})
    w = results.get("weights", {})
    lines = [f"env {results['env']}  seed {results['seed']}  ratio source: {results['ratio']['source']}"]
    if "regret" in f:
        lines += [
            f"return        {f['return']:.4f} ± {f['return_ci']:.4f}   (exact optimum {f['optimal_return_exact']:.4f})",
            f"paired regret {f['regret']:.4f} ± {f['regret_ci']:.4f}",
            f"Q̂ error / spread of Q*: expert {100 * f['q_error_expert']:.1f}%  behaviour {100 * f['q_error_behaviour']:.1f}%"
            f"   bias on expert {f['q_bias_expert']:+.3f}",
        ]
    elif "return" in f:
        lines.append(f"return {f['return']:.2f} ± {f['return_ci']:.2f} over the evaluation episodes")
    if w:
        lines.append(
            f"weights over D: mean {w['mean_behaviour']:.3f}  ESS {w['ess']:.0f} ({100 * w['ess_fraction']:.2f}%)  max {w['max']:.3g}"
        )
    r = results.get("ratio", {})
    if "ratio_relative_l2" in r:
        lines.append(
            f"ŵ vs true ratio: relative L2 error {r['ratio_relative_l2']:.3f}  behaviour mean {r['ratio_mean_behaviour']:.3f}"
        )
    if "wall_seconds" in results:
        lines.append(f"wall time {results['wall_seconds']:.1f} s (data {results.get('data_seconds', 0):.1f} s)")
    return "\n".join(lines)

"""The studies' reports on synthetic results: the convergence slopes' bootstrap intervals, the paper tables' learning
curves and "budget and convergence" table, and the LQR tables over every LQR env that ran.

No training: each test writes the ``results.json`` / ``history.json`` fields the report reads into ``tmp_path``.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from torchrl_wbrm.configs import CONFIG_DIR

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "recipes"))

import convergence_study  # noqa: E402
import paper_tables  # noqa: E402
from studies import paper_tables_report  # noqa: E402

SIZES = [1000, 2000, 4000, 8000, 16000, 32000]


# ---------------------------------------------------------------------- convergence_study: bootstrap slopes
def _synthetic(noise: float, runs: int = 5, slope: float = -0.5, seed: int = 0):
    """error = 3 n^slope, times log-normal noise of scale ``noise``, ``runs`` runs per size."""
    rng = np.random.default_rng(seed)
    sizes = np.repeat(SIZES, runs)
    return sizes, 3.0 * sizes.astype(float) ** slope * np.exp(rng.normal(0.0, noise, sizes.size))


def test_bootstrap_slope_recovers_a_known_slope_and_widens_with_noise():
    quiet = convergence_study.bootstrap_slope(*_synthetic(0.05))
    noisy = convergence_study.bootstrap_slope(*_synthetic(0.4))
    for ci in (quiet, noisy):
        assert ci.low < ci.slope < ci.high
        assert ci.low <= -0.5 <= ci.high, ci
    assert abs(quiet.slope + 0.5) < 0.02
    assert (noisy.high - noisy.low) > 4 * (quiet.high - quiet.low)
    assert quiet.high - quiet.low > 0.005  # an interval, not a point
    # the least-squares slope is fit_slope's, and the interval is reproducible (numpy seed fixed)
    sizes, errors = _synthetic(0.4)
    assert noisy.slope == pytest.approx(convergence_study.fit_slope(sizes, errors))
    assert convergence_study.bootstrap_slope(sizes, errors) == noisy
    assert convergence_study.bootstrap_slope(sizes, errors, seed=1) != noisy


def test_bootstrap_slope_resamples_within_each_size():
    """Two runs per size, one exactly on n^-1 and one on 2 n^-1 at every size: any within-size resample keeps the
    slope -1 (a resample across sizes would not), so the interval is the point -1."""
    sizes = np.repeat(SIZES, 2)
    errors = np.array([c / n for n in SIZES for c in (1.0, 2.0)])
    ci = convergence_study.bootstrap_slope(sizes, errors, resamples=500)
    assert ci.slope == pytest.approx(-1.0)
    assert ci.high - ci.low < 0.35 and ci.low <= -1.0 + 1e-9 and ci.high >= -1.0 - 1e-9
    one = convergence_study.bootstrap_slope(SIZES, [1.0 / n for n in SIZES])
    assert np.isnan(one.low) and "one run per size" in one.format()
    with pytest.raises(ValueError, match="two sizes"):
        convergence_study.bootstrap_slope([1000, 1000], [0.1, 0.2])


def test_convergence_report_writes_the_slopes_with_their_intervals(tmp_path):
    sizes, errors = _synthetic(0.2, runs=3)
    records = [(kind, int(n), seed % 3, {"ratio": {"ratio_relative_l2": float(e)}, "final": {"q_error_expert": float(e)}})
               for kind in ("ratio", "q") for seed, (n, e) in enumerate(zip(sizes, errors))]
    text = convergence_study.report(records, tmp_path)
    ci = convergence_study.bootstrap_slope(sizes, errors)
    assert (tmp_path / "convergence.png").is_file()
    md = (tmp_path / "convergence.md").read_text()
    assert md.strip() == text.strip()
    assert f"| ratio | {ci.format()} | α=1: −1/6, α=2: −1/4, α→∞: −1/2 |" in md
    assert f"| q | {ci.format()} | β=1: −1/6, β=2: −1/4, β→∞: −1/2 |" in md
    assert f"Fitted log-log slopes: ratio: {ci.format()}, q: {ci.format()}" in md
    assert "| ratio | 1000 | 3 |" in md


def test_convergence_cells_take_the_sizes():
    cells = convergence_study.build_cells(False, ratio_sizes=[500, 5000], q_sizes=[3000])
    assert [(c["block"], c["n"]) for c in cells] == [("ratio", 500), ("ratio", 5000), ("q", 3000)]
    assert [c["n"] for c in convergence_study.build_cells(True)] == SIZES[:2] * 2


# ---------------------------------------------------------------------- paper_tables: curves and LQR envs
def _run(out: Path, env: str, algo: str, seed: int, curve: dict[int, float], *, steps: int | None = None,
         lqr: bool = True, optimum: float = 85.0) -> None:
    """A fake run: results.json with the fields the report reads, history.json with ``curve`` as its q stage."""
    run = out / env / algo / f"seed{seed}"
    run.mkdir(parents=True)
    metric = "regret" if lqr else "return"
    last = curve[max(curve)]
    final = ({"regret": last, "return": optimum - last, "optimal_return_exact": optimum, "q_error_expert": 0.1,
              "q_bias_expert": -0.1, "q_bias_behaviour": 0.2} if lqr else {"return": last})
    results = {"status": "finished", "env": env, "algo": algo, "seed": seed, "final": final, "wall_seconds": 10.0,
               "config": {"env": {"name": env, "kind": "lqr" if lqr else "mountain_car"},
                          "q": {"steps": steps or max(curve)}}}
    (run / "results.json").write_text(json.dumps(results))
    history = [{"stage": "ratio", "step": 5, "held_out_loss": 0.3}]
    history += [{"stage": "q_train", "step": s, "loss": 1.0} for s in curve]
    history += [{"stage": "q", "step": s, metric: v, f"{metric}_ci": 0.01} for s, v in curve.items()]
    (run / "history.json").write_text(json.dumps(history))


def test_learning_curves_and_the_budget_table_on_synthetic_runs(tmp_path):
    # wbrm on lqr_exp1: regret 0.4, 0.2, 0.1, 0.095 (seed 0) and 0.6, 0.4, 0.3, 0.305 (seed 1): flat at the end
    _run(tmp_path, "lqr_exp1", "wbrm", 0, {500: 0.4, 1000: 0.2, 1500: 0.1, 2000: 0.095})
    _run(tmp_path, "lqr_exp1", "wbrm", 1, {500: 0.6, 1000: 0.4, 1500: 0.3, 2000: 0.305})
    # td3bc: still falling (0.2 -> 0.1) ; fqi: past its best (0.05 at step 1000, then 0.2)
    _run(tmp_path, "lqr_exp1", "td3bc", 0, {500: 0.4, 1000: 0.3, 1500: 0.2, 2000: 0.1})
    _run(tmp_path, "lqr_exp1", "fqi", 0, {500: 0.1, 1000: 0.05, 1500: 0.1, 2000: 0.2}, steps=2000)
    # iql: the last two agree (×1.05) but both are far above the best, at step 500: past its best, not flat
    _run(tmp_path, "lqr_exp1", "iql", 0, {500: 0.05, 1000: 0.2, 1500: 0.4, 2000: 0.42})
    # MountainCar return: 80 -> 90 -> 93, budget 3000 (a chosen, longer budget)
    _run(tmp_path, "mountain_car", "wbrm", 0, {1000: 80.0, 2000: 90.0, 3000: 93.0}, lqr=False)

    from torchrl_wbrm.training.reporting import load_results

    curves = paper_tables_report.learning_curves(load_results(tmp_path))
    wbrm = curves[("lqr_exp1", "wbrm")]
    assert wbrm["metric"] == "regret" and wbrm["steps"] == [500, 1000, 1500, 2000] and wbrm["budget"] == [2000]
    assert wbrm["mean"] == pytest.approx([0.5, 0.3, 0.2, 0.2]) and wbrm["n"] == [2, 2, 2, 2]
    assert wbrm["low"][0] < 0.5 < wbrm["high"][0]  # a Student-t band over the two seeds
    assert wbrm["high"][0] - wbrm["low"][0] == pytest.approx(2 * 12.706 * 0.1, rel=1e-3)
    assert curves[("mountain_car", "wbrm")]["metric"] == "return"
    assert curves[("mountain_car", "wbrm")]["budget"] == [3000]

    verdicts = {k: paper_tables_report.curve_verdict(c) for k, c in curves.items()}
    # wbrm: the seeds' changes -0.005 and +0.005 average 0, a paired interval over the two seeds covers it: flat
    wbrm_v = verdicts[("lqr_exp1", "wbrm")]
    assert wbrm_v["verdict"] == "flat" and wbrm_v["vs_previous"][0] == pytest.approx(0.0, abs=1e-12)
    assert wbrm_v["vs_previous"][1] == pytest.approx(-12.706 * 0.005, rel=1e-3)  # t(1) x the se of (-0.005, 0.005)
    # one seed: the two evaluations' own intervals (0.01 each) combined, ±0.01·√2
    td3bc = verdicts[("lqr_exp1", "td3bc")]
    assert td3bc["verdict"] == "still improving"
    assert td3bc["vs_previous"] == pytest.approx((-0.1, -0.1 - 0.01 * 2 ** 0.5, -0.1 + 0.01 * 2 ** 0.5))
    fqi = verdicts[("lqr_exp1", "fqi")]
    assert fqi["verdict"] == "past its best" and fqi["best_step"] == 1000 and fqi["vs_best"][0] == pytest.approx(0.15)
    iql = verdicts[("lqr_exp1", "iql")]
    assert iql["verdict"] == "past its best" and iql["vs_previous"][0] == pytest.approx(0.02) and iql["best_step"] == 500
    car = verdicts[("mountain_car", "wbrm")]
    assert car["verdict"] == "still improving" and car["vs_previous"][0] == pytest.approx(3.0)
    assert car["best"] == pytest.approx(90.0)

    text = paper_tables_report.tables(tmp_path)
    assert "### Budget and convergence" in text
    assert ("| lqr_exp1 | fqi | regret | 2000 | 4 | 0.1000 | 0.2000 | 0.0500 (1000) | +0.1000 [+0.0859, +0.1141] "
            "| +0.1500 [+0.1359, +0.1641] | past its best |") in text
    assert ("| lqr_exp1 | wbrm | regret | 2000 | 4 | 0.2000 | 0.2000 | 0.2000 (1500) | +0.0000 [-0.0635, +0.0635] "
            "| +0.0000 [-0.0635, +0.0635] | flat |") in text
    assert ("| mountain_car | wbrm | return | 3000 | 3 | 90.00 | 93.00 | 90.00 (2000) | +3.00 [+2.99, +3.01] "
            "| +3.00 [+2.99, +3.01] | still improving |") in text

    path = paper_tables_report.plot_learning_curves(tmp_path)
    assert path == tmp_path / "learning_curves.png" and path.stat().st_size > 10_000


def test_a_change_within_the_evaluation_noise_is_flat_not_past_its_best(tmp_path):
    """Regret 0.002 at step 1500 and 0.005 at 2000 is ×2.5, but each evaluation's own interval is ±0.01: the
    verdict is flat. The same change with ±0.001 intervals is past its best."""
    _run(tmp_path / "noisy", "lqr_exp1", "brm", 0, {1500: 0.002, 2000: 0.005})
    _run(tmp_path / "sharp", "lqr_exp1", "brm", 0, {1500: 0.002, 2000: 0.005})
    history = tmp_path / "sharp" / "lqr_exp1" / "brm" / "seed0" / "history.json"
    history.write_text(history.read_text().replace('"regret_ci": 0.01', '"regret_ci": 0.001'))
    from torchrl_wbrm.training.reporting import load_results

    noisy = paper_tables_report.learning_curves(load_results(tmp_path / "noisy"))[("lqr_exp1", "brm")]
    sharp = paper_tables_report.learning_curves(load_results(tmp_path / "sharp"))[("lqr_exp1", "brm")]
    assert paper_tables_report.curve_verdict(noisy)["verdict"] == "flat"
    assert paper_tables_report.curve_verdict(sharp)["verdict"] == "past its best"


def test_the_budget_check_compares_whole_runs_at_other_budgets(tmp_path):
    """The grid's runs at 2000 steps and the check's own runs at 1000 and 4000: td3bc is better at 4000 beyond the
    paired interval (not converged), wbrm moves within the noise (converged), fqi is worse with more steps; the
    check's runs stay out of the grid's tables."""
    out = tmp_path / "paper_tables"
    check = paper_tables_report.budget_check_dir(out)
    assert check == tmp_path / "paper_tables_budget_check"
    finals = {"td3bc": {1000: [0.09, 0.11, 0.10], 2000: [0.05, 0.07, 0.06], 4000: [0.02, 0.03, 0.025]},
              "wbrm": {1000: [0.02, 0.03, 0.01], 2000: [0.010, 0.012, 0.008], 4000: [0.011, 0.009, 0.010]},
              "fqi": {2000: [0.010, 0.011, 0.012], 4000: [0.020, 0.022, 0.021]}}
    for algo, by_steps in finals.items():
        for steps, values in by_steps.items():
            root = out if steps == 2000 else check / f"steps{steps}"
            for seed, v in enumerate(values):
                _run(root, "lqr_exp1", algo, seed, {steps: v})
    _run(out, "lqr_exp2", "wbrm", 0, {2000: 0.5})  # an env the check did not run: not in its table
    curves = paper_tables_report.budget_curves(out)
    assert set(curves) == {("lqr_exp1", "td3bc"), ("lqr_exp1", "wbrm"), ("lqr_exp1", "fqi")}
    assert curves[("lqr_exp1", "td3bc")]["runs"][4000] == {0: 0.02, 1: 0.03, 2: 0.025}
    verdicts = {a: paper_tables_report.budget_verdict(curves[("lqr_exp1", a)], 2000) for a in finals}
    assert verdicts["td3bc"]["verdict"] == "not converged" and verdicts["td3bc"]["longest"] == 4000
    assert verdicts["td3bc"]["change"][0] == pytest.approx(-0.035)
    assert verdicts["wbrm"]["verdict"] == "converged"
    assert verdicts["fqi"]["verdict"] == "worse with more steps"
    assert paper_tables_report.budget_verdict({"metric": "regret", "runs": {2000: {0: 0.1}}}, 2000)["verdict"] == "n/a"

    from torchrl_wbrm.training.reporting import load_results

    records = load_results(out)
    assert paper_tables_report.table_budget(records) == 2000
    assert {r["config"]["q"]["steps"] for r in records} == {2000}  # the grid's tables read the grid's runs only
    text = paper_tables_report.tables(out)
    assert "### Budget check" in text
    assert "| env | algorithm | figure | 1000 steps | 2000 steps (table) | 4000 steps | largest − 2000 [95% CI] |" in text
    assert "| lqr_exp1 | fqi | regret | – | 0.0110 ± 0.0025 | 0.0210 ± 0.0025 | +0.0100 [" in text
    assert "| lqr_exp1 | td3bc | regret | 0.1000 ± 0.0248 | 0.0600 ± 0.0248 | 0.0250 ± 0.0124 |" in text
    path = paper_tables_report.plot_budget_check(out, 2000)
    assert path == out / "budget_check.png" and path.stat().st_size > 10_000
    assert paper_tables_report.budget_table(tmp_path / "elsewhere", 2000) == ""  # no check ran: no section


def test_the_learning_curves_figure_draws_a_panel_per_env_and_a_line_per_budget(tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _run(tmp_path, "lqr_exp1", "wbrm", 0, {500: 0.4, 1000: 0.2})
    _run(tmp_path, "lqr_exp1", "brm", 0, {500: 0.5, 1000: 0.3, 1500: 0.25}, steps=1500)
    _run(tmp_path, "mountain_car", "wbrm", 0, {1000: 80.0, 2000: 90.0}, lqr=False)
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # keep the figure to look at it
    paper_tables_report.plot_learning_curves(tmp_path)
    (fig,) = figures
    lqr, car = fig.axes
    assert lqr.get_yscale() == "log" and car.get_yscale() == "linear"
    assert "lqr_exp1" in lqr.get_title() and "mountain_car" in car.get_title()
    # two curves and a vertical line at each budget (1000 for wbrm, 1500 for brm) in the LQR panel
    vertical = sorted(line.get_xdata()[0] for line in lqr.get_lines() if line.get_linestyle() == "--")
    assert vertical == [1000, 1500]
    curves = [line for line in lqr.get_lines() if line.get_linestyle() == "-"]
    assert sorted(len(line.get_xdata()) for line in curves) == [2, 3]
    assert sorted(t.get_text() for t in fig.legends[0].get_texts()) == ["brm", "wbrm"]


def test_paper_tables_cover_every_lqr_env_that_ran(tmp_path):
    """A run of lqr_nondiag (not in the paper) enters Table 2 and every LQR table with its own exact optimum, and
    the figures; the default envs include it."""
    assert "lqr_nondiag" in paper_tables.DEFAULT_ENVS
    assert (CONFIG_DIR / "env" / "lqr_nondiag.yaml").is_file()
    _run(tmp_path, "lqr_exp1", "wbrm", 0, {1000: 0.02, 2000: 0.01}, optimum=85.435)
    _run(tmp_path, "lqr_nondiag", "wbrm", 0, {1000: 0.5, 2000: 0.25}, optimum=71.25)
    _run(tmp_path, "lqr_nondiag", "td3bc", 0, {1000: 0.5, 2000: 0.125}, optimum=71.25)
    text = paper_tables_report.tables(tmp_path)
    assert "| algorithm | lqr_exp1 return | lqr_nondiag return | paper (exp1, exp2, exp3) |" in text
    assert "| exact optimum | 85.435 | 71.250 | 87.84 (the reward cap) |" in text
    assert "| wbrm | 85.425 | 71.000 | 86.65, 86.74, 87.10 |" in text
    assert "| td3bc | – | 71.125 | – |" in text
    for title in ("paired regret", "Q̂ error", "on expert samples", "on behaviour samples"):
        block = next(part for part in text.split("### ") if part.startswith("LQR: ") and title in part)
        assert "| algorithm | lqr_exp1 | lqr_nondiag |" in block, title
    assert "| td3bc | – | 0.1250 |" in text  # the regret table
    assert "Table 3" not in text
    assert "| lqr_nondiag | td3bc | regret | 2000 | 2 |" in text
    paper_tables_report.plot(tmp_path)
    assert (tmp_path / "paper_tables.png").is_file()


def test_the_headline_puts_every_method_on_every_env_beside_the_exact_optimum(tmp_path):
    """The headline (the first table of tables.md): LQR regret and MountainCar return per algorithm, the exact
    optimum's row first, the best mean of each column in bold (lowest regret, highest return)."""
    for seed, (w, t) in enumerate([(0.02, 0.05), (0.04, 0.03)]):
        _run(tmp_path, "lqr_exp1", "wbrm", seed, {2000: w}, optimum=85.435)
        _run(tmp_path, "lqr_exp1", "td3bc", seed, {2000: t}, optimum=85.435)
    _run(tmp_path, "mountain_car", "wbrm", 0, {2000: 90.0}, lqr=False)
    _run(tmp_path, "mountain_car", "td3bc", 0, {2000: 95.0}, lqr=False)
    text = paper_tables_report.tables(tmp_path)
    assert text.startswith("### Headline")
    head = text.split("\n\n")[1].splitlines()
    assert head[0] == "| algorithm | lqr_exp1 regret | mountain_car return |"
    assert head[2] == "| exact optimum | 0 (return 85.435) | – (none known) |"
    # wbrm's mean regret 0.03 < td3bc's 0.04: bold; td3bc's return 95 > 90: bold
    assert head[3] == "| td3bc | 0.0400 ± 0.1271 | **95.00** |"
    assert head[4] == "| wbrm | **0.0300 ± 0.1271** | 90.00 |"


def test_an_lqr_env_is_known_by_its_config_not_its_name():
    assert paper_tables_report.is_lqr({"env": "my_system", "config": {"env": {"kind": "lqr"}}})
    assert not paper_tables_report.is_lqr({"env": "lqr_like_name", "config": {"env": {"kind": "mountain_car"}}})
    assert paper_tables_report.is_lqr({"env": "x", "final": {"optimal_return_exact": 1.0}})  # results without a config
    lqr, other = paper_tables_report.split_envs([
        {"env": "lqr_nondiag", "config": {"env": {"kind": "lqr"}}}, {"env": "lqr_exp2", "config": {"env": {"kind": "lqr"}}},
        {"env": "mountain_car", "config": {"env": {"kind": "mountain_car"}}}])
    assert lqr == ["lqr_exp2", "lqr_nondiag"] and other == ["mountain_car"]


# ---------------------------------------------------------------------- weighting_study: each label's shaping
def test_weighting_study_levels_set_the_shaping_their_labels_name():
    """A level's label holds whatever the recipe's default shaping is (ŵ^0.25 today): the paper's ŵ and the exact
    w are untempered, unclipped and unmixed; each shaped level changes exactly the named part."""
    from hydra import compose, initialize_config_dir

    import weighting_study
    from torchrl_wbrm.training import register_configs

    register_configs()
    expected = {  # label -> (source, temper, clip, mix)
        "learned ŵ (paper)": ("learned", 1.0, None, 0.0),
        "exact w": ("exact", 1.0, None, 0.0),
        "learned ŵ^0.25 (the recipe's default)": ("learned", 0.25, None, 0.0),
        "learned min(ŵ, 10)": ("learned", 1.0, 10.0, 0.0),
        "learned ½ + ½ŵ": ("learned", 1.0, None, 0.5),
        "exact ½ + ½w": ("exact", 1.0, None, 0.5),
        "learned ŵ + BC": ("learned", 1.0, None, 0.0),
    }
    cells = weighting_study.build_cells(quick=False)
    seen = set()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        default = compose("wbrm_offline").ratio
        for cell in cells:
            label = cell["method"]
            if label not in expected:
                continue
            ratio = compose("wbrm_offline", overrides=cell["overrides"]).ratio
            assert (ratio.source, ratio.temper, ratio.clip, ratio.mix) == expected[label], (cell["block"], label)
            seen.add(label)
    assert seen == set(expected)
    # the guard is needed: the recipe's default shaping is not the paper's
    assert (default.temper, default.clip, default.mix) != (1.0, None, 0.0)


def test_weighting_study_runs_the_blocks_asked_for():
    import weighting_study

    regimes = weighting_study.build_cells(quick=False, blocks=["regimes"])
    assert regimes and {c["block"] for c in regimes} == {"regimes"}
    assert len(regimes) == len(weighting_study.REGIMES) * len(weighting_study.REGIME_METHODS)
    every = weighting_study.build_cells(quick=False)
    assert {c["block"] for c in every} == set(weighting_study.BLOCKS)
    with pytest.raises(ValueError, match="unknown \\['regime'\\]"):
        weighting_study.build_cells(quick=False, blocks=["regime"])
    # some regimes only: the shifted starts, each run with every regime method
    wide = "behaviour start wide (x₀ ~ N(0, 3² I))"
    some = weighting_study.build_cells(quick=False, blocks=["regimes"], regimes=[wide])
    assert {c["setting"] for c in some} == {wide} and len(some) == len(weighting_study.REGIME_METHODS)
    assert all("env.lqr_data.behaviour_initial_std=3.0" in c["overrides"] for c in some)
    with pytest.raises(ValueError, match="unknown \\['shifted'\\]"):
        weighting_study.build_cells(quick=False, blocks=["regimes"], regimes=["shifted"])
    two = ["unweighted", "learned ŵ^0.25 (the recipe's default)"]
    pair = weighting_study.build_cells(quick=False, blocks=["regimes"], regimes=[wide], methods=two)
    assert [c["method"] for c in pair] == two
    with pytest.raises(ValueError, match="methods: unknown \\['raw'\\]"):
        weighting_study.build_cells(quick=False, blocks=["regimes"], methods=["raw"])


def test_weighting_study_pairs_each_method_with_the_unweighted_residual_over_seeds():
    """Per (block, env, setting), each method minus ``unweighted`` seed by seed: a method better on every seed by a
    steady margin is ``better`` even where the per-method intervals overlap (the seeds share most of the spread); a
    noisy difference is a ``tie``; a seed only one side ran is left out; MountainCar (no regret) is not paired."""
    import weighting_study

    def rec(setting, method, seed, regret, q_error, env="lqr_exp1"):
        final = {"regret": regret, "q_error_expert": q_error} if env != "mountain_car" else {"return": regret}
        return {"status": "finished", "seed": seed, "final": final,
                "study": {"block": "regimes", "env": env, "setting": setting, "method": method}}

    base = [0.02, 0.05, 0.03, 0.04]  # a wide seed-to-seed spread
    records = [rec("wide", "unweighted", k, v, 0.3) for k, v in enumerate(base)]
    records += [rec("wide", "steady", k, v - 0.01, 0.3 + 0.05 * (-1) ** k) for k, v in enumerate(base)]
    records += [rec("wide", "steady", 9, 0.0, 0.0)]  # no unweighted run of seed 9: not paired
    records += [rec("car", m, k, 90.0, 0.0, env="mountain_car") for m in ("unweighted", "steady") for k in range(3)]
    text = weighting_study.paired_table(records)
    row = next(line for line in text.splitlines() if "| steady |" in line)
    assert row.startswith("| regimes | lqr_exp1 | wide | steady | 4 | -0.0100 [-0.0100, -0.0100] better | ")
    assert row.endswith(" tie |") and "car" not in text
    from torchrl_wbrm.training.reporting import results_table

    per_method = results_table(records[:8], ["=study.method"], {"regret": "final.regret"})
    assert "0.0250 ± 0.0205" in per_method and "0.0350 ± 0.0205" in per_method  # unpaired: the intervals overlap
    records += [rec("wide", "worse", k, v + 0.02 + 0.001 * k, 0.3) for k, v in enumerate(base)]
    worse = next(line for line in weighting_study.paired_table(records).splitlines() if "| worse |" in line)
    assert "| worse | 4 | +0.0215 [" in worse and worse.endswith("] worse | +0.0000 [+0.0000, +0.0000] tie |")
    assert weighting_study.paired_table([r for r in records if r["study"]["method"] != "unweighted"]) == ""


def test_weighting_study_reports_a_regimes_only_run_without_a_figure(tmp_path):
    """``--blocks regimes`` alone: the tables hold the regimes and the paired table; the weighting block's figure is
    not drawn (there is nothing to draw), where it used to fail on zero panels after every run had finished."""
    import weighting_study

    for seed, (unweighted, default) in enumerate([(0.03, 0.02), (0.05, 0.04), (0.04, 0.03)]):
        for method, regret in (("unweighted", unweighted), ("learned ŵ^0.25 (the recipe's default)", default)):
            run = tmp_path / "regimes" / "lqr_exp1" / "wide" / method.replace(" ", "_") / f"seed{seed}"
            run.mkdir(parents=True)
            (run / "results.json").write_text(json.dumps({
                "status": "finished", "seed": seed, "final": {"regret": regret, "q_error_expert": 0.2},
                "study": {"block": "regimes", "env": "lqr_exp1", "setting": "wide", "method": method}}))
    assert weighting_study.plot(tmp_path) is None
    text = weighting_study.tables(tmp_path)
    assert "### Regimes (LQR exp1)" in text and "-0.0100 [-0.0100, -0.0100] better" in text


# ---------------------------------------------------------------------- q_accuracy_study: one change per search
def _q_record(block, method, env, seed, residual, wall=30.0):
    return {"study": {"block": block, "env": env, "setting": block, "method": method}, "seed": seed,
            "final": {"held_out_bellman_residual": residual}, "wall_seconds": wall}


def _q_records(levels):
    """The base on two systems and seeds 0-2 (residual 1.0), and each ``(block, level, factor, wall)`` with its
    residual ``factor`` × the base's, jittered by ±0.1% so that its paired interval is narrow but not zero."""
    records = [_q_record("default", "default", env, seed, 1.0) for env in ("lqr_exp1", "lqr_exp2") for seed in range(3)]
    for block, level, factor, wall in levels:
        for env in ("lqr_exp1", "lqr_exp2"):
            for seed, jitter in zip(range(3), (0.999, 1.0, 1.001)):
                records.append(_q_record(block, level, env, seed, factor * jitter, wall))
    return records


def test_q_accuracy_adopt_takes_one_level_and_breaks_ties_by_run_time():
    from studies import q_accuracy_report as q

    # two candidates whose intervals overlap: the cheaper one, although its score is higher
    chosen = q.adopt(_q_records([("activation", "GELU", 0.985, 30.0), ("step budget", "6000", 0.984, 60.0)]))
    assert chosen[:2] == ("activation", "GELU") and len(chosen[2]) == 2
    # a candidate lower beyond the other's interval wins whatever it costs
    chosen = q.adopt(_q_records([("activation", "GELU", 0.985, 30.0), ("step budget", "6000", 0.90, 60.0)]))
    assert chosen[:2] == ("step budget", "6000")
    # a level above the base is no candidate; no candidate, no change
    assert q.adopt(_q_records([("activation", "ReLU", 1.05, 30.0)])) is None


def test_paper_tables_overrides_go_last_on_every_run():
    """``--overrides`` reach every cell of the grid and of the budget check, after the cell's own settings (so they
    win), and every budget-check run keeps its own step budget after them."""
    out = Path("results/x")
    lagrange = "baselines.cql.with_lagrange=true"
    cells = paper_tables.build_cells(["lqr_exp1", "mountain_car"], ["cql", "brm"], out, False, [lagrange])
    assert len(cells) == 4 and all(c["overrides"][-1] == lagrange for c in cells)
    assert all(lagrange not in c["overrides"] for c in paper_tables.build_cells(["lqr_exp1"], ["cql"], out, False))
    budget = paper_tables.build_budget_cells(["lqr_exp1"], ["cql"], out, False, 4000, [lagrange])
    assert budget[0]["overrides"][-3:] == [lagrange, "q.steps=4000", "q.eval_every=4000"]

"""The detector's variation between grid nodes as noise along the path: the fit
recovers a known process, the noise stays put while the aircraft stands still, and
in table rollouts it turns a score just under the threshold into flags that come
and go (and braking on them into stops), seeded and reproducible."""

import numpy as np
import pytest

from reachwatch.diagrams import load_scenario
from reachwatch.reach.score_noise import ScoreNoise, fit_score_noise, logit
from reachwatch.taxi import dynamics_for, taxi_guarded_rollouts, paper_grid


def _ou_runs(sigma, length, mean=0.0, runs=40, ticks=160, step=0.25, seed=0):
    """Runs of a known process: logit(real) = logit(table) + mean + OU(sigma, length)
    over a path advancing ``step`` per tick."""
    rng = np.random.default_rng(seed)
    noise_model = ScoreNoise(sigma, length, mean)
    real, table, travelled = [], [], []
    for _ in range(runs):
        base = rng.uniform(0.05, 0.9, ticks)
        noise, path = None, []
        for _ in range(ticks):
            noise = noise_model.step(noise, np.array([step]), rng)
            path.append(noise[0])
        real.append(noise_model.apply(base, np.array(path)))
        table.append(base)
        travelled.append(step * np.arange(ticks))
    return real, table, travelled


def test_fit_recovers_a_known_process():
    fitted = fit_score_noise(*_ou_runs(0.55, 2.4))
    assert fitted.sigma == pytest.approx(0.55, rel=0.1)
    assert fitted.length == pytest.approx(2.4, rel=0.2)
    assert abs(fitted.mean) < 0.1
    other = fit_score_noise(*_ou_runs(0.3, 8.0, mean=-0.4, seed=1))
    assert other.sigma == pytest.approx(0.3, rel=0.1) and other.length == pytest.approx(8.0, rel=0.25)
    assert other.mean == pytest.approx(-0.4, abs=0.1)


def test_noise_stays_put_at_standstill_and_keeps_its_spread_when_moving():
    model, rng = ScoreNoise(0.5, 2.0), np.random.default_rng(3)
    first = model.step(None, np.zeros(20000), rng)
    assert np.std(first) == pytest.approx(0.5, rel=0.03)
    np.testing.assert_array_equal(model.step(first, np.zeros(20000), rng), first)
    later = model.step(first, np.full(20000, 2.0), rng)          # one length on
    assert np.std(later) == pytest.approx(0.5, rel=0.03)
    assert np.corrcoef(first, later)[0, 1] == pytest.approx(np.exp(-1.0), abs=0.03)
    np.testing.assert_allclose(model.apply([0.2, 0.5], np.zeros(2)), [0.2, 0.5])
    np.testing.assert_allclose(ScoreNoise(0.5, 2.0, mean=np.log(3.0)).apply([0.5], [0.0]), [0.75])
    assert logit(0.5) == 0.0


def test_noise_keeps_saturated_and_extreme_scores_in_place():
    """Before: `apply` went through `logit`'s clip at 1e-4, so every score above 0.9999
    came out at 0.9999 whatever the noise: a threshold of 0.99995 was never reached
    with noise and always without. Now a saturated score stays saturated, and a small
    noise moves an extreme score by a small amount, on the side of its sign."""
    model = ScoreNoise(0.5, 2.0)
    np.testing.assert_array_equal(model.apply([0.0, 1.0], [3.0, -3.0]), [0.0, 1.0])
    high, low = model.apply([0.99995, 5e-5], [1e-6, -1e-6])
    assert 0.99995 < high < 0.99995 + 1e-9 and 5e-5 - 1e-9 < low < 5e-5
    assert np.isfinite(model.apply([0.3, 0.7], [1e4, -1e4])).all()


@pytest.mark.parametrize("field, value", [("sigma", 0.0), ("sigma", -1.0), ("length", np.inf),
                                          ("length", True), ("sigma", "0.5"), ("mean", np.nan)])
def test_bad_noise_parameters_are_named(field, value):
    kw = {"sigma": 0.5, "length": 2.0, field: value}
    with pytest.raises(ValueError, match=f"ScoreNoise.{field} must be a finite number"):
        ScoreNoise(**kw)


def test_fit_refuses_what_it_cannot_fit():
    with pytest.raises(ValueError, match="equal length"):
        fit_score_noise([np.ones(5)], [np.ones(4)], [np.arange(5.0)])
    with pytest.raises(ValueError, match="at least 10"):
        fit_score_noise([np.full(5, 0.3)], [np.full(5, 0.2)], [np.arange(5.0)])
    with pytest.raises(ValueError, match="no noise"):
        fit_score_noise([np.full(50, 0.3)], [np.full(50, 0.3)], [np.arange(50.0)])
    rng = np.random.default_rng(0)
    white = [rng.uniform(0.1, 0.9, 200) for _ in range(5)]
    with pytest.raises(ValueError, match="uncorrelated"):
        fit_score_noise(white, [np.full(200, 0.5)] * 5, [np.arange(200.0)] * 5)


def test_noise_in_table_rollouts_makes_flags_come_and_go():
    """A straight run along the centreline, where the swept score sits just under the
    threshold everywhere: without noise, never flagged and never stopped; with the
    noise, flagged on part of the ticks, and braking on those flags stops some runs
    (the noise freezes once they stand still). Same seed, same outcomes."""
    scenario = load_scenario(data="")
    dynamics = dynamics_for(scenario)
    grid = paper_grid(10.0, (3, 3, 3))
    steer, score = np.zeros(grid.shape), np.full(grid.shape, 0.45)
    starts = np.column_stack([np.zeros(200), np.full(200, 100.0), np.zeros(200)])
    kw = dict(threshold=0.5, strategy="brake", horizon=8.0, starts=starts)
    plain = taxi_guarded_rollouts(grid, dynamics, steer, score, **kw)
    assert plain.flagged_ticks.sum() == 0 and not plain.stopped.any()
    noise = ScoreNoise(0.6, 3.0)
    noisy = taxi_guarded_rollouts(grid, dynamics, steer, score, score_noise=noise, seed=5, **kw)
    share = noisy.flagged_ticks.sum() / noisy.ticks.sum()
    assert 0.2 < share < 0.6                       # about P(N(0, 0.6) > logit(.5) - logit(.45))
    assert 0 < noisy.stopped.sum() < len(starts)
    again = taxi_guarded_rollouts(grid, dynamics, steer, score, score_noise=noise, seed=5, **kw)
    np.testing.assert_array_equal(again.flagged_ticks, noisy.flagged_ticks)
    np.testing.assert_array_equal(again.stopped, noisy.stopped)
    other = taxi_guarded_rollouts(grid, dynamics, steer, score, score_noise=noise, seed=6, **kw)
    assert not np.array_equal(other.flagged_ticks, noisy.flagged_ticks)


def test_score_along_real_runs_and_the_fit_from_them(detector_path, tmp_path):
    """In the rendered loop: the score logged at a run's first tick is the guarded
    sweep's score at that node; runs are NaN-padded past their end and cached; the
    fit of real against swept scores runs end to end on them."""
    from reachwatch.reach import InlineExecutor
    from reachwatch.taxi import sweep_guarded
    from reachwatch.taxi.fidelity import real_score_noise, score_runs
    from reachwatch.taxi.guarded import SCORE_PORT
    scenario = load_scenario(data=f"monitor: {{detector: {detector_path}, threshold: 0.5}}\n")
    grid = paper_grid(scenario.environment.half_width, (3, 3, 3))
    tables = sweep_guarded(scenario, grid, cache_dir=tmp_path / "sweeps",
                           executor=InlineExecutor(), progress=False)
    nodes = grid.states([13, 10])
    out = score_runs(scenario, np.vstack([nodes, [[30.0, 100.0, 0.0]]]), duration=1.0,
                     cache_dir=tmp_path / "scores", progress=False)
    assert out["score"].shape == (3, 21) and out["state"].shape == (3, 21, 3)
    assert not out["engaged"].any()
    np.testing.assert_allclose(out["score"][:2, 0], np.asarray(tables[SCORE_PORT]).ravel()[[13, 10]],
                               rtol=1e-5, atol=1e-6)
    assert out["ticks"].tolist()[2] == 0 and np.isnan(out["score"][2]).all()
    for i in range(2):
        assert np.isfinite(out["score"][i, :out["ticks"][i]]).all()
        assert np.isnan(out["score"][i, out["ticks"][i]:]).all()
    starts = grid.states([13, 12, 14])
    noise, fit = real_score_noise(scenario, grid, tables[SCORE_PORT], starts, duration=1.0,
                                  cache_dir=tmp_path / "outcomes", progress=False)
    assert fit == {"runs": 3, "ticks": 3 * 21, "cut_at_box": 0, "left_out": 0}
    assert noise.sigma > 0 and noise.length > 0
    # the runs do not depend on what the monitor does with the score: another threshold
    # and fallback read the same cached runs (one cache folder) and fit the same noise
    other = load_scenario(data=f"monitor: {{detector: {detector_path}, threshold: 0.2, "
                               f"strategy: brake}}\n")
    assert real_score_noise(other, grid, tables[SCORE_PORT], starts, duration=1.0,
                            cache_dir=tmp_path / "outcomes", progress=False) == (noise, fit)
    assert len(list((tmp_path / "outcomes").iterdir())) == 1
    # the trade-off curves with noise: a vanishing noise gives the plain curves back (a
    # faint upward offset: the quantile thresholds are node scores, so a node's own score
    # ties with one, and the plain comparison, score >= threshold, flags a tie); the
    # fitted one keeps the thresholds and moves the figures
    from reachwatch.taxi import TaxiApplication
    tradeoff_curves = TaxiApplication().tradeoff_curves
    kw = dict(mission_limit=2.0)
    plain = tradeoff_curves(scenario, grid, tables, 1.0, ["brake"], 3, **kw)
    faint = tradeoff_curves(scenario, grid, tables, 1.0, ["brake"], 3,
                            score_noise=ScoreNoise(sigma=1e-12, length=1.0, mean=1e-7), **kw)
    assert faint == plain
    noisy = tradeoff_curves(scenario, grid, tables, 1.0, ["brake"], 3, score_noise=noise,
                            seed=1, **kw)
    assert [r["threshold"] for r in noisy["brake"]] == [r["threshold"] for r in plain["brake"]]
    assert noisy == tradeoff_curves(scenario, grid, tables, 1.0, ["brake"], 3,
                                    score_noise=noise, seed=1, **kw)      # seeded


def test_guard_check_refuses_no_noise_seeds(tmp_path):
    from reachwatch.pipeline.online_stages import guard_check
    with pytest.raises(ValueError, match="noise_seeds must be >= 1, got 0"):
        guard_check(None, None, None, ["brake"], starts=2, seed=0, horizon=1.0, mission_limit=None,
                    cache_dir=tmp_path, noise_starts=2, noise_seeds=0)
    assert not any(tmp_path.iterdir())              # refused before any work


def test_the_fit_from_runs_stops_each_run_at_its_first_tick_outside_the_box():
    """Past the box the table has no score (interpolation takes the edge's): a run counts
    up to its first tick outside, a run that starts outside not at all, and the counts
    say how many were cut."""
    from reachwatch.reach import Grid
    from reachwatch.reach.score_noise import fit_score_noise_on_runs
    grid = Grid(lo=[0.0], hi=[60.0], shape=[61])
    table = np.full(61, 0.5)
    rng, process = np.random.default_rng(3), ScoreNoise(0.5, 3.0, 0.0)
    real = []
    for _ in range(30):                         # the known process about the table's 0.5
        noise, path = None, []
        for _ in range(160):
            noise = process.step(noise, np.array([0.25]), rng)
            path.append(noise[0])
        real.append(process.apply(np.full(160, 0.5), np.array(path)))
    paths = [(0.25 * np.arange(160))[:, None] for _ in real]      # 0 to 39.75: inside
    paths[0] = paths[0] + 30.0                    # 60 (the edge) at tick 120, past it after
    paths[1] = paths[1] - 1.0                                     # outside at its first
    scores = [np.array(r) for r in real]
    # the score beyond the box is nonsense: were it used, the fit would see it
    scores[0][121:] = 0.999
    noise, fit = fit_score_noise_on_runs(grid, table, paths, scores, np.full(30, 160),
                                         lambda path: 0.25 * np.arange(len(path)))
    assert fit == {"runs": 29, "ticks": 28 * 160 + 121, "cut_at_box": 2}
    assert noise.sigma == pytest.approx(0.5, rel=0.15)

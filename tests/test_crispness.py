"""Map crispness (mean map entropy, plane thickness) against a brute-force numpy version on small maps."""

import math
import time

import numpy as np
import pytest

from neld_jax.judging.crispness import crispness, entropy_over_query_draws, per_scan_means, sample_queries
from neld_jax.judging.judge import (
    crispest,
    crispest_over_draws,
    crispness_margins,
    describe_margin,
    every_scan_crispness,
    map_crispness,
    margin_over_draws,
    warn_if_not_crispest,
)


def _brute_force(points, radius, min_neighbors):
    entropy, thickness = [], []
    for p in points:
        near = points[np.linalg.norm(points - p, axis=1) <= radius]
        if len(near) < min_neighbors:
            entropy.append(np.nan)
            thickness.append(np.nan)
            continue
        cov = np.cov(near.T, bias=True)
        entropy.append(0.5 * math.log(np.linalg.det(2 * math.pi * math.e * cov)))
        thickness.append(math.sqrt(np.linalg.eigvalsh(cov)[0]))
    return np.array(entropy), np.array(thickness)


def test_matches_brute_force_on_a_small_map():
    rng = np.random.default_rng(0)
    # A noisy plane, a noisy blob and a few isolated points (skipped: too few neighbours), far from the origin
    # so that the centring matters.
    plane = np.c_[rng.uniform(0, 2, (300, 2)), rng.normal(0, 0.02, 300)]
    blob = rng.normal(0, 0.1, (100, 3)) + [3.0, 0.0, 0.0]
    lonely = np.array([[10.0, 10.0, 10.0], [20.0, 0.0, 0.0]])
    points = np.concatenate([plane, blob, lonely]) + [5e5, 4e6, 30.0]
    result = crispness(points, radius=0.3, min_neighbors=5, max_queries=0)
    entropy, thickness = _brute_force(points, 0.3, 5)
    np.testing.assert_array_equal(np.isnan(result.entropy), np.isnan(entropy))
    assert np.isnan(entropy[-2:]).all()
    valid = ~np.isnan(entropy)
    np.testing.assert_allclose(result.entropy[valid], entropy[valid], atol=1e-6)
    np.testing.assert_allclose(result.thickness[valid], thickness[valid], atol=1e-7)
    summary = result.summary()
    assert summary["queries_skipped"] == int((~valid).sum())
    assert summary["mean_map_entropy"] == pytest.approx(entropy[valid].mean())


def test_misregistration_makes_the_map_less_crisp():
    rng = np.random.default_rng(1)
    wall = np.c_[rng.uniform(0, 4, (2000, 2)), rng.normal(0, 0.005, 2000)]
    shifted = wall + [0.0, 0.0, 0.05]  # a second scan of the same wall, 5 cm off
    aligned = crispness(np.concatenate([wall, wall + rng.normal(0, 0.005, wall.shape)]), seed=3)
    smeared = crispness(np.concatenate([wall, shifted]), seed=3)
    assert smeared.summary()["mean_map_entropy"] > aligned.summary()["mean_map_entropy"] + 0.5
    assert smeared.summary()["mean_plane_thickness_m"] == pytest.approx(0.025, abs=0.004)


def test_entropy_over_query_draws_pairs_the_maps_on_each_draw(capsys):
    rng = np.random.default_rng(4)
    wall = np.c_[rng.uniform(0, 4, (3000, 2)), rng.normal(0, 0.005, 3000)]
    maps = {
        "aligned": np.concatenate([wall, wall + rng.normal(0, 0.005, wall.shape)]),
        "smeared": np.concatenate([wall, wall + [0.0, 0.0, 0.03]]),
    }
    entropy = entropy_over_query_draws(maps, seeds=[0, 5, 9], max_queries=400, radius=0.3)
    assert set(entropy) == {"aligned", "smeared"} and entropy["aligned"].shape == (3,)
    # each draw is crispness() on that seed's queries, the same points for both maps
    for i, seed in enumerate([0, 5, 9]):
        queries = sample_queries(6000, 400, seed)
        for name, points in maps.items():
            expected = crispness(points, radius=0.3, query_index=queries).summary()["mean_map_entropy"]
            assert entropy[name][i] == pytest.approx(expected)
    assert len(set(entropy["aligned"].round(9))) == 3  # the draws differ
    assert (entropy["smeared"] > entropy["aligned"]).all()
    with pytest.raises(ValueError, match="sizes differ"):
        entropy_over_query_draws({"a": wall, "b": wall[:-1]}, seeds=[0])
    assert capsys.readouterr().err == ""  # quiet unless asked; a run asks for a bar over the draws
    shown = entropy_over_query_draws(maps, seeds=[0, 5, 9], max_queries=400, radius=0.3, progress=True)
    assert "crispness over query draws" in capsys.readouterr().err
    np.testing.assert_array_equal(shown["smeared"], entropy["smeared"])


def test_crispness_margins_compare_the_answer_with_each_method_on_every_draw():
    import ml_collections

    rng = np.random.default_rng(5)
    wall = np.c_[rng.uniform(0, 4, (1500, 2)), rng.normal(0, 0.005, 1500)]
    seq = ml_collections.ConfigDict({"scans": [wall, wall + rng.normal(0, 0.005, wall.shape)], "num_scans": 2})
    shifted = np.tile(np.eye(4), (2, 1, 1))
    shifted[1, 2, 3] = 0.03  # the second scan 3 cm off the wall
    methods = {"initial": shifted, "optimized": np.tile(np.eye(4), (2, 1, 1))}
    eval_cfg = {"crispness_draws": 4, "crispness_queries": 300, "crispness_radius_m": 0.3}
    margins = crispness_margins(seq, methods, eval_cfg)
    assert set(margins) == {"initial"}
    margin = margins["initial"]
    assert len(margin["per_draw"]) == 4 and all(d < -0.5 for d in margin["per_draw"])
    assert margin["all_draws_agree"] and margin["mean"] == pytest.approx(np.mean(margin["per_draw"]), abs=1e-6)
    assert "crisper on every one of 4 draws" in describe_margin("initial", margin)
    assert crispness_margins(seq, methods, {**eval_cfg, "crispness_draws": 1}) == {}
    # draw 0 taken from map_crispness's summaries (as the run does) instead of measured again: the same margins
    summaries, _ = map_crispness(seq, methods, eval_cfg)
    reused = crispness_margins(seq, methods, eval_cfg, first_draw=summaries)["initial"]
    assert reused["per_draw"] == pytest.approx(margin["per_draw"], abs=1e-6)
    tie = {"per_draw": [0.001, -0.002], "mean": -0.0005, "std": 0.002, "all_draws_agree": False}
    assert "a tie: the 2 draws disagree in sign" in describe_margin("baseline", tie)


def test_the_map_of_every_scan_keeps_the_same_points_of_each_scan_for_every_method():
    # Six scans of one wall, the fourth 3 cm off under "odometry": the map of every scan sees it, on the same
    # `points_per_scan` points of each scan whichever poses register them.
    rng = np.random.default_rng(2)
    scans = [np.c_[rng.uniform(0, 4, (800, 2)), rng.normal(0, 0.004, 800)] for _ in range(6)]
    good = np.tile(np.eye(4), (6, 1, 1))
    off = good.copy()
    off[3, 2, 3] = 0.03
    eval_cfg = {"crispness_draws": 3, "crispness_queries": 500, "crispness_radius_m": 0.3}
    crisp, margins = every_scan_crispness(
        scans, {"odometry": off, "refined": good}, eval_cfg, against="refined", points_per_scan=300
    )
    assert crisp["refined"]["mean_map_entropy"] < crisp["odometry"]["mean_map_entropy"]
    assert margins["odometry"]["all_draws_agree"] and margins["odometry"]["mean"] < 0
    # the same points: a map of the scans cut to those 300 points by hand scores the same
    cut = [s[np.sort(np.random.default_rng(i).permutation(len(s))[:300])] for i, s in enumerate(scans)]
    by_hand, _ = map_crispness(type("Scans", (), {"scans": cut}), {"refined": good}, eval_cfg)
    assert by_hand["refined"]["mean_map_entropy"] == pytest.approx(crisp["refined"]["mean_map_entropy"], abs=1e-9)


def test_the_margins_stop_drawing_at_the_runs_deadline(caplog):
    import ml_collections

    rng = np.random.default_rng(6)
    wall = np.c_[rng.uniform(0, 4, (1500, 2)), rng.normal(0, 0.005, 1500)]
    seq = ml_collections.ConfigDict({"scans": [wall, wall.copy()], "num_scans": 2})
    methods = {"initial": np.tile(np.eye(4), (2, 1, 1)), "optimized": np.tile(np.eye(4), (2, 1, 1))}
    eval_cfg = {"crispness_draws": 4, "crispness_queries": 300, "crispness_radius_m": 0.3}
    past = time.perf_counter() - 1.0
    assert {
        name: len(v) for name, v in entropy_over_query_draws({"a": wall, "b": wall}, [0, 1], 300, deadline=past).items()
    } == {"a": 0, "b": 0}
    summaries, _ = map_crispness(seq, methods, eval_cfg)
    with caplog.at_level("WARNING", logger="neld_jax.judging.judge"):
        assert crispness_margins(seq, methods, eval_cfg, first_draw=summaries, deadline=past) == {}
    assert "1 of 4 query draws fit the run's clock" in caplog.text and "no margin without two" in caplog.text
    far = time.perf_counter() + 3600.0
    margins = crispness_margins(seq, methods, eval_cfg, first_draw=summaries, deadline=far)
    assert len(margins["initial"]["per_draw"]) == 4


def test_no_draw_starts_that_would_end_past_the_deadline(monkeypatch):
    """Each draw is timed; the next starts only if one as long would end by the deadline (a fake clock: 5 s a
    reading, so a draw takes 5 s and the second would start at 10 s and end at 15 s)."""
    import types

    from neld_jax.judging import crispness as crispness_module

    readings = iter(np.arange(0.0, 100.0, 5.0))
    monkeypatch.setattr(crispness_module, "time", types.SimpleNamespace(perf_counter=lambda: float(next(readings))))
    rng = np.random.default_rng(7)
    wall = np.c_[rng.uniform(0, 4, (600, 2)), rng.normal(0, 0.005, 600)]
    drawn = entropy_over_query_draws({"a": wall}, [0, 1, 2], 100, deadline=12.0)
    assert len(drawn["a"]) == 1
    assert len(entropy_over_query_draws({"a": wall}, [0, 1, 2], 100, deadline=60.0)["a"]) == 3


def test_each_maps_tree_is_built_once_for_all_draws(monkeypatch):
    from neld_jax.judging import crispness as crispness_module

    built, original = [], crispness_module.cKDTree

    def counting_tree(points):
        built.append(len(points))
        return original(points)

    monkeypatch.setattr(crispness_module, "cKDTree", counting_tree)
    wall = np.c_[np.random.default_rng(7).uniform(0, 4, (800, 2)), np.zeros(800)]
    entropy = entropy_over_query_draws({"a": wall, "b": wall + 0.001}, [0, 1, 2], 200)
    assert {name: len(v) for name, v in entropy.items()} == {"a": 3, "b": 3} and built == [800, 800]


def test_query_sampling_and_per_scan_means():
    np.testing.assert_array_equal(sample_queries(5, 10), np.arange(5))
    picked = sample_queries(1000, 50, seed=2)
    assert len(picked) == 50 and np.all(np.diff(picked) > 0)
    np.testing.assert_array_equal(picked, sample_queries(1000, 50, seed=2))
    values = np.array([1.0, 3.0, np.nan, 5.0])
    means = per_scan_means(values, np.array([0, 1, 2, 3]), np.array([0, 0, 1, 1]), num_scans=3)
    np.testing.assert_allclose(means[:2], [2.0, 5.0])
    assert np.isnan(means[2])


def test_a_run_names_the_crispest_poses_and_warns_when_they_are_not_its_own(caplog):
    summaries = {
        "initial": {"mean_map_entropy": -3.42},
        "baseline": {"mean_map_entropy": -3.49},
        "optimized": {"mean_map_entropy": -3.475},
    }
    with caplog.at_level("WARNING", logger="neld_jax.judging.judge"):
        assert warn_if_not_crispest(summaries) == "baseline"
    assert "poses_baseline.txt" in caplog.text and "-3.490" in caplog.text and "-3.475" in caplog.text
    caplog.clear()
    summaries["optimized"]["mean_map_entropy"] = -3.5
    with caplog.at_level("WARNING", logger="neld_jax.judging.judge"):
        assert warn_if_not_crispest(summaries) == "optimized"
    assert caplog.text == ""
    assert crispest({"initial": {"mean_map_entropy": None}}) is None


def test_the_crispest_poses_are_judged_over_the_query_draws_and_a_tie_is_not_warned_about(caplog):
    # Draw 0 alone puts the baseline ahead (-3.49 against -3.475); over five draws the difference changes sign.
    summaries = {
        "initial": {"mean_map_entropy": -3.42},
        "baseline": {"mean_map_entropy": -3.49},
        "optimized": {"mean_map_entropy": -3.475},
    }
    tie = {
        "initial": margin_over_draws([-0.05, -0.04, -0.06, -0.05, -0.05]),
        "baseline": margin_over_draws([0.015, -0.002, -0.001, 0.001, -0.003]),
    }
    with caplog.at_level("INFO", logger="neld_jax.judging.judge"):
        assert warn_if_not_crispest(summaries, margins=tie) == "baseline"  # the lower mean, but a tie
    assert "WARNING" not in caplog.text and "a tie" in caplog.text and "poses_baseline.txt" in caplog.text
    caplog.clear()
    # Every draw puts the baseline ahead: a warning, with the mean over the draws.
    ahead = dict(tie, baseline=margin_over_draws([0.015, 0.002, 0.001, 0.004, 0.003]))
    with caplog.at_level("WARNING", logger="neld_jax.judging.judge"):
        assert warn_if_not_crispest(summaries, margins=ahead) == "baseline"
    assert "poses_baseline.txt" in caplog.text and "0.00500 on average over 5 query draws" in caplog.text
    caplog.clear()
    # The mean over the draws below every other method's: NeLD-BA's own poses, though draw 0 says otherwise.
    behind = dict(tie, baseline=margin_over_draws([0.001, -0.004, -0.003, -0.002, -0.004]))
    with caplog.at_level("INFO", logger="neld_jax.judging.judge"):
        assert warn_if_not_crispest(summaries, margins=behind) == "optimized"
    assert caplog.text == ""
    assert crispest_over_draws({}) is None

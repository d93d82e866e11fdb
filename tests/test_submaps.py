"""The plan of cubes (training.submaps): one cube for a sequence it holds, else windows; the switch, the windows,
the per-cube ray tensors, loop-closure submaps, and a run over submaps end to end. The trainer's side of submaps is
in tests/test_train.py."""

import logging

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neld_jax.config import defaults
from neld_jax.data.sequence import Sequence
from neld_jax.errors import ConfigError
from neld_jax.field.normalize import NORMALIZATION_MARGIN, fit_normalization
from neld_jax.training import submaps
from neld_jax.training.rays import sphere_scene_rays


def _line_of_scans(num_scans=12, spacing=5.0, radius=4.0, seed=0):
    """Scans along the x axis, spacing metres apart: each a ring of points `radius` around its sensor."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (num_scans, 1, 1))
    poses[:, 0, 3] = spacing * np.arange(num_scans)
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.1, (num_scans, 3))).as_matrix()
    d = rng.normal(size=(num_scans, 50, 3))
    scans = list(radius * d / np.linalg.norm(d, axis=-1, keepdims=True))
    return scans, poses


def test_windows_cover_every_keyframe_with_the_overlap():
    for s, w, o in [(10, 4, 2), (17, 3, 1), (5, 5, 2), (3, 8, 1), (50, 7, 3)]:
        starts = submaps.window_starts(s, w, o)
        covered = np.zeros(s, int)
        for a in starts:
            covered[a : a + min(w, s)] += 1
        assert covered.min() >= 1 and starts[-1] + min(w, s) == s
        assert np.all(np.diff(starts) <= w - o) and np.all(np.diff(starts) >= 1)
    with pytest.raises(ConfigError, match="overlap"):
        submaps.window_starts(10, 3, 3)


def test_max_window_keeps_every_window_under_the_extent():
    scans, poses = _line_of_scans(12, spacing=5.0, radius=4.0)
    lower, upper = submaps.scan_bounds(scans, poses)
    # A window of W scans spans about 5 (W - 1) + 8 m along x.
    w = submaps.max_window(lower, upper, 25.0)
    assert w == 4
    assert submaps.max_window(lower, upper, 5.0) == 0  # one scan alone (8 m) is larger
    assert submaps.max_window(lower, upper, 1e6) == 12
    # One fast stretch (a 20 m jump): the strict rule shrinks every window, the 10% quantile ignores it.
    scans, poses = _line_of_scans(40, spacing=5.0, radius=4.0)
    poses[20:, 0, 3] += 15.0
    lower, upper = submaps.scan_bounds(scans, poses)
    assert submaps.max_window(lower, upper, 25.0) == 1
    assert submaps.max_window(lower, upper, 25.0, quantile=0.1) == 4


def test_plan_normalises_each_submap_and_pads_for_devices():
    scans, poses = _line_of_scans(17)
    plan = submaps.plan_submaps(scans, poses, 3, 1, 0.9, num_devices=3)
    assert plan.members.shape == (9, 3) and list(plan.weight) == [1.0] * 8 + [0.0]
    assert submaps.mesh_size(plan, 3) == 3 and submaps.mesh_size(plan, 64) == 8
    for row, norm in zip(plan.members, plan.norms):
        pts = np.vstack([s @ p[:3, :3].T + p[:3, 3] for s, p in zip([scans[i] for i in row], poses[row])])
        assert np.abs(norm.points_to_normalized(pts)).max() <= 0.9 + 1e-9  # its scans fit its cube
    assert np.all(submaps.describe_membership(plan, 17) >= 1)
    assert plan.ref_scale == pytest.approx(np.median(plan.scales[:8]))


def test_switch_rule_and_log_line(caplog):
    c = defaults()
    c.model.pos_freqs = 10
    c.submaps.max_detail_m = 0.25  # one cube up to 2 * 0.9 * 0.25 * 2^8 = 115 m
    assert submaps.max_submap_extent_m(0.25, 10, 0.9) == pytest.approx(115.2)
    assert not submaps.submaps_wanted(c, 100.0) and submaps.submaps_wanted(c, 130.0)
    c.submaps.enabled = "off"
    assert not submaps.submaps_wanted(c, 1e4)
    c.submaps.enabled = "on"
    assert submaps.submaps_wanted(c, 1.0)
    c.submaps.enabled = "maybe"
    with pytest.raises(ConfigError, match="submaps.enabled"):
        submaps.submaps_wanted(c, 1.0)

    c.submaps.enabled = "auto"
    c.submaps.max_detail_m = 0.1  # cubes of at most 46 m: a line of 12 scans 5 m apart (63 m) is split
    scans, poses = _line_of_scans(12)
    seq = Sequence(scans=scans, poses=poses, name="line")
    with caplog.at_level(logging.INFO, logger="neld_jax.training.submaps"):
        plan = submaps.plan_from_config(seq, c)
    assert plan.num_submaps > 1 and plan.window == submaps.max_window(*submaps.scan_bounds(scans, poses), 46.08, 0.1)
    assert any("split into" in r.message and f"{plan.num_submaps} submaps" in r.message for r in caplog.records)
    c.submaps.max_detail_m = 1.0  # one cube holds it: a plan of one submap, the whole sequence's normalisation
    one = submaps.plan_from_config(seq, c)
    norm = fit_normalization(scans, poses, NORMALIZATION_MARGIN)
    assert one.num_submaps == 1 and list(one.members[0]) == list(range(12)) and one.rho_factor[0] == 1.0
    assert one.norms[0].scale == one.ref_scale == norm.scale and np.allclose(one.norms[0].offset, norm.offset)
    c.submaps.max_detail_m, c.submaps.overlap = 0.01, 2  # 4.6 m cubes: not even one 8 m scan fits
    with caplog.at_level(logging.WARNING, logger="neld_jax.training.submaps"):
        plan = submaps.plan_from_config(seq, c)
    assert plan.window == 3 and any("data.max_range_m" in r.message for r in caplog.records)


def test_max_submaps_lengthens_the_windows(caplog):
    # A step draws rays from every submap, so the cpu budget caps their number: the windows grow instead.
    c = defaults()
    c.model.pos_freqs, c.submaps.max_detail_m, c.submaps.overlap = 10, 0.04, 1  # 18 m cubes: 6 windows of 3
    scans, poses = _line_of_scans(12)
    seq = Sequence(scans=scans, poses=poses, name="line")
    free = submaps.plan_from_config(seq, c)
    assert free.num_submaps > 3
    c.submaps.max_submaps = 3
    with caplog.at_level(logging.INFO, logger="neld_jax.training.submaps"):
        capped = submaps.plan_from_config(seq, c)
    assert capped.num_submaps <= 3 and capped.window > free.window
    assert submaps.count_submaps(poses, capped.window - 1, 1, c.submaps.closure_radius_m) > 3  # the smallest such
    assert any("max_submaps=3" in r.message for r in caplog.records)
    assert submaps.window_for_limit(poses, 2, 1, 0.0, 1) == 12  # at worst one window holds the whole sequence
    c.submaps.keyframes = 2  # an explicit window is kept
    assert submaps.plan_from_config(seq, c).window == 2


def test_submap_arrays_hold_each_window_s_rays_in_its_units():
    rays, T = sphere_scene_rays(6, 20, seed=0)
    rays.ranges = rays.ranges.astype(np.float32)
    scans = [rays.directions[rays.scan_index == s] * rays.ranges[rays.scan_index == s, None] for s in range(6)]
    plan = submaps.plan_submaps(scans, T, 4, 2, 0.9)
    a = submaps.submap_arrays(plan, rays, T)
    assert a.directions.shape == (2, 80, 3) and list(a.num_rays) == [80, 80]
    for m, (row, norm) in enumerate(zip(plan.members, plan.norms)):
        for slot, s in enumerate(row):
            mine = a.scan_index[m, : a.num_rays[m]] == slot
            np.testing.assert_allclose(
                a.ranges[m, : a.num_rays[m]][mine], rays.ranges[rays.scan_index == s] * norm.scale, rtol=1e-6
            )


def test_run_with_submaps_writes_the_single_cube_outputs_within_its_time(tmp_path, monkeypatch):
    """A run whose submaps are switched on: one pose per input scan, one raw and one rendered map. On a fake training
    clock (1 s a step, 5 s a compile) its 100 steps do not fit in the training share of max_minutes: the loop trains
    a shorter plan whole, and metrics.json says which (the rendered map uses that plan's window); config.json keeps
    the steps asked for."""
    import json

    from conftest import fake_training_clock, make_tiny_config

    from neld_jax import run
    from neld_jax.data.poses import read_tum

    fake_training_clock(monkeypatch)
    cfg = make_tiny_config(str(tmp_path / "run"), steps=100)
    cfg.data.synthetic.num_scans = 5
    cfg.sampling.coarse_stages, cfg.sampling.fine_stages = (8,), (4,)  # one stage
    cfg.train.fixed_scans = ()
    cfg.train.log_every, cfg.train.checkpoint_every = 10, 0
    cfg.max_minutes = 2.0  # training until 90 s (30 s kept for the crispness draws), the map's limit after it
    cfg.submaps.enabled, cfg.submaps.keyframes, cfg.submaps.overlap = "on", 3, 1
    # The map's time limit, already over after the first of its parts: every submap renders that quarter of
    # the rays (a uniform sample), and the run says how many it rendered.
    cfg.mapping.max_seconds = 1e-9
    summary = run.run(cfg, progress=False)["run"]
    assert summary["submaps"] == 2 and not summary["stopped_early"]
    assert summary["map_rays_rendered"] == len(np.array_split(np.arange(summary["map_rays"]), 4)[0])
    assert 30 <= summary["schedule_steps"] < 100 and summary["steps"] == summary["schedule_steps"]
    assert json.loads((tmp_path / "run" / "config.json").read_text())["train"]["steps"] == 100
    last = json.loads((tmp_path / "run" / "history.json").read_text())[-1]
    assert last["alpha"] == cfg.model.pos_freqs
    assert 0 < last["range_residual_median_m"] < float("inf")  # logged beside the mean, as a single cube's
    for name in ("poses_optimized.txt", "map_raw.ply", "map_rendered.ply", "metrics.json", "scans_report.csv"):
        assert (tmp_path / "run" / name).is_file(), name
    _, T_opt = read_tum(tmp_path / "run" / "poses_optimized.txt")
    _, T_initial = read_tum(tmp_path / "run" / "poses_initial.txt")
    assert T_opt.shape == (5, 4, 4)
    np.testing.assert_allclose(T_opt[0], T_initial[0], atol=1e-6)  # anchored on scan 0
    assert np.abs(T_opt[1:] - T_initial[1:]).max() > 1e-6


def test_long_courtyard_route_switches_submaps_on_by_itself():
    """The generic cpu config on the long synthetic route splits it without any submap flag."""
    from configs.generic import get_config
    from neld_jax.synthetic.generator import make_sequence

    seq = make_sequence(
        {
            "route": "courtyards",
            "route_length_m": 600.0,
            "num_scans": 100,
            "num_beams": 4,
            "num_columns": 90,
            "max_range_m": 30.0,
            "gt_map_points": 0,
        }
    )
    steps = np.linalg.norm(np.diff(seq.gt_poses[:, :3, 3], axis=0), axis=1)
    assert np.allclose(steps, 6.0, atol=0.1)  # 600 m in 100 even steps (the loop closes: 99 steps + one back)
    assert np.linalg.norm(seq.gt_poses[0, :3, 3] - seq.gt_poses[-1, :3, 3]) == pytest.approx(6.0, abs=0.1)
    assert min(len(s) for s in seq.scans) > 50  # walls, buildings and ground within 30 m everywhere
    config = get_config("cpu")
    config.data.max_range_m = 30.0
    plan = submaps.plan_from_config(seq, config)
    assert plan.num_submaps >= 5
    assert np.all(submaps.describe_membership(plan, seq.num_scans) >= 1)


def test_a_revisit_gets_a_submap_holding_both_visits():
    # A closed loop of 40 keyframes: the last ones come back to the first.
    angle = 2 * np.pi * np.arange(40) / 40
    poses = np.tile(np.eye(4), (40, 1, 1))
    poses[:, 0, 3], poses[:, 1, 3] = 30 * np.cos(angle), 30 * np.sin(angle)
    scans = [np.random.default_rng(s).normal(size=(20, 3)) for s in range(40)]
    assert submaps.closure_pairs(poses, 6, 0.0) == []
    pairs = submaps.closure_pairs(poses, 6, 10.0)
    assert pairs == [(0, 39)]  # keyframe 0 and 39 are 4.7 m apart; (1, 39), (0, 38) ... are the same revisit
    plan = submaps.plan_submaps(scans, poses, 6, 2, 0.9, closure_radius_m=10.0)
    assert plan.num_submaps == len(submaps.window_starts(40, 6, 2)) + 1
    last = plan.members[-1]
    assert list(last) == [0, 1, 2, 37, 38, 39]  # half a window around each visit

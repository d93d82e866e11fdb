"""Submaps (neld_jax.submaps, neld_jax.submap_train): the split, the switch, the shared pose's map into each
submap's frame, and, on 8 simulated CPU devices in a subprocess, the sharded step, the shared scan's gradient and
resume with sharded state (tests/submap_devices_check.py)."""

import dataclasses
import logging
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neld_jax import submap_train, submaps
from neld_jax.config import base_config
from neld_jax.data.normalize import fit_normalization
from neld_jax.data.rays import sphere_scene_rays
from neld_jax.data.sequence import Sequence
from neld_jax.errors import ConfigError

from conftest import similarity_scale

HERE = os.path.dirname(os.path.abspath(__file__))


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
            covered[a:a + min(w, s)] += 1
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


def test_shared_pose_maps_exactly_into_each_submap_frame():
    """The submap step's pose, mapped back to the world with its normalisation, is T_init @ Exp(xi) in metres."""
    scans, poses = _line_of_scans(10)
    plan = submaps.plan_submaps(scans, poses, 4, 2, 0.9)
    rng = np.random.default_rng(1)
    xi = np.concatenate([rng.normal(0, 0.02, (10, 3)), rng.normal(0, 0.05, (10, 3))], axis=1).astype(np.float32)
    world = submaps.global_poses(poses, xi, plan.ref_scale)
    for row, norm, factor in zip(plan.members, plan.norms, plan.rho_factor):
        T_n = submap_train.submap_scan_poses(jnp.asarray(xi), jnp.asarray(norm.poses_to_normalized(poses[row]),
                                                                          jnp.float32),
                                             jnp.asarray(row), jnp.float32(factor))
        back = norm.poses_to_world(np.asarray(T_n, np.float64))
        np.testing.assert_allclose(back[:, :3, :3], world[row, :3, :3], atol=2e-6)
        np.testing.assert_allclose(back[:, :3, 3], world[row, :3, 3], atol=1e-4)  # metres; float32 in a ~10 m cube
    # A pure translation rho moves the sensor by rho / s_ref metres along its own axes.
    xi_t = np.zeros((10, 6))
    xi_t[:, 0] = plan.ref_scale  # one metre along the body x axis
    moved = submaps.global_poses(poses, xi_t, plan.ref_scale)
    np.testing.assert_allclose(moved[:, :3, 3] - poses[:, :3, 3], poses[:, :3, 0], atol=1e-12)


def test_switch_rule_and_log_line(caplog):
    c = base_config()
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
    norm = fit_normalization(scans, poses, 0.9)
    with caplog.at_level(logging.INFO, logger="neld_jax.submaps"):
        plan = submaps.plan_from_config(seq, norm, c)
    assert plan is not None and plan.window == submaps.max_window(*submaps.scan_bounds(scans, poses), 46.08, 0.1)
    assert any("split into" in r.message and f"{plan.num_submaps} submaps" in r.message for r in caplog.records)
    c.submaps.max_detail_m = 1.0
    assert submaps.plan_from_config(seq, norm, c) is None
    c.submaps.max_detail_m, c.submaps.overlap = 0.01, 2  # 4.6 m cubes: not even one 8 m scan fits
    with caplog.at_level(logging.WARNING, logger="neld_jax.submaps"):
        plan = submaps.plan_from_config(seq, norm, c)
    assert plan.window == 3 and any("data.max_range_m" in r.message for r in caplog.records)


def test_max_submaps_lengthens_the_windows(caplog):
    # A step draws rays from every submap, so the cpu budget caps their number: the windows grow instead.
    c = base_config()
    c.model.pos_freqs, c.submaps.max_detail_m, c.submaps.overlap = 10, 0.04, 1  # 18 m cubes: 6 windows of 3
    scans, poses = _line_of_scans(12)
    seq = Sequence(scans=scans, poses=poses, name="line")
    norm = fit_normalization(scans, poses, 0.9)
    free = submaps.plan_from_config(seq, norm, c)
    assert free.num_submaps > 3
    c.submaps.max_submaps = 3
    with caplog.at_level(logging.INFO, logger="neld_jax.submaps"):
        capped = submaps.plan_from_config(seq, norm, c)
    assert capped.num_submaps <= 3 and capped.window > free.window
    assert submaps.count_submaps(poses, capped.window - 1, 1, c.submaps.closure_radius_m) > 3  # the smallest such
    assert any("max_submaps=3" in r.message for r in caplog.records)
    assert submaps.window_for_limit(poses, 2, 1, 0.0, 1) == 12  # at worst one window holds the whole sequence
    c.submaps.keyframes = 2  # an explicit window is kept
    assert submaps.plan_from_config(seq, norm, c).window == 2


def test_submap_arrays_hold_each_window_s_rays_in_its_units():
    rays, T = sphere_scene_rays(6, 20, seed=0)
    rays.ranges = rays.ranges.astype(np.float32)
    scans = [rays.directions[rays.scan_index == s] * rays.ranges[rays.scan_index == s, None] for s in range(6)]
    plan = submaps.plan_submaps(scans, T, 4, 2, 0.9)
    a = submaps.submap_arrays(plan, rays, T)
    assert a.directions.shape == (2, 80, 3) and list(a.num_rays) == [80, 80]
    for m, (row, norm) in enumerate(zip(plan.members, plan.norms)):
        for slot, s in enumerate(row):
            sl = slice(a.scan_start[m, slot], a.scan_start[m, slot] + a.scan_count[m, slot])
            np.testing.assert_allclose(a.ranges[m, sl], rays.ranges[rays.scan_index == s] * norm.scale, rtol=1e-6)
            assert np.all(a.scan_index[m, sl] == slot)


def test_owner_is_the_most_central_cube():
    scans, poses = _line_of_scans(10)
    plan = submaps.plan_submaps(scans, poses, 4, 2, 0.9)
    centre = [n.offset for n in plan.norms]
    points = np.stack([centre[0], centre[1], centre[-1]])
    candidates = np.array([[0, 1], [0, 1], [2, 3]])
    assert list(submaps.owner_submap(points, plan, candidates)) == [0, 1, 3]


def test_sharded_step_shared_scan_and_resume_on_8_devices(tmp_path):
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=8", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, os.path.join(HERE, "submap_devices_check.py"), str(tmp_path)],
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for check in ("sharded step equals unsharded", "shared scan gradient", "resume with sharded state"):
        assert f"OK {check}" in proc.stdout, proc.stdout


def test_submaps_share_the_step_s_rays():
    c = base_config()
    c.train.batch_rays, c.submaps.batch_rays = 512, 0
    assert submap_train.submap_batch_rays(c, 1) == 512
    assert submap_train.submap_batch_rays(c, 13) == 39  # 507 rays a step, about the single cube's 512
    assert submap_train.submap_batch_rays(c, 172) == submap_train.MIN_SUBMAP_BATCH_RAYS == 8
    c.submaps.batch_rays = 128  # set explicitly: each submap draws that many
    assert submap_train.submap_batch_rays(c, 13) == 128
    c.submaps.batch_rays, c.submaps.step_rays_factor = 0, 3.0  # the cpu budget's: 1536 rays a step
    assert submap_train.submap_batch_rays(c, 31) == 49


def test_submap_fields_take_their_own_width():
    # The cpu budget trades the submap fields' width for rays (submaps.width); the single cube keeps model.width.
    from configs import lio_keyframes

    cpu, gpu = lio_keyframes.get_config("cpu"), lio_keyframes.get_config("gpu")
    assert (cpu.submaps.width, cpu.model.width, gpu.submaps.width) == (64, 128, 0)
    assert submap_train.make_submap_field(cpu).width == 64 and submap_train.make_field(cpu).width == 128
    assert submap_train.make_submap_field(gpu).width == gpu.model.width
    setup = submap_train.create_submap_state(cpu, num_scans=4, num_submaps=2)
    widths = {leaf.shape[-1] for leaf in jax.tree.leaves(setup.state.params["fields"]) if leaf.ndim == 3}
    assert 64 in widths and 128 not in widths  # [M, fan_in, 64] kernels (the heads' outputs are narrower)


def test_submap_runs_take_their_own_termination_weight():
    # lio_keyframes' cpu budget weighs the termination loss 3x in one cube and keeps the paper's 1 in submap runs.
    from configs import lio_keyframes

    cpu = lio_keyframes.get_config("cpu")
    assert submap_train.submap_loss_settings(cpu).lambda_termination == 1.0
    assert submap_train.LossSettings.from_config(cpu.loss).lambda_termination == 3.0
    cpu.submaps.lambda_termination = 0.0  # unset: the single cube's weight
    assert submap_train.submap_loss_settings(cpu) == submap_train.LossSettings.from_config(cpu.loss)


def test_real_recordings_fields_learn_at_four_times_the_cpu_budgets_rate():
    """lio_keyframes' cpu budget: every field, one cube or submaps (both take train.field_lr_*), at four times the
    cpu budget's rate at its 1500 steps; the gpu budget: its own rate."""
    from neld_jax.config import apply_budget, base_config
    from configs import lio_keyframes

    config = apply_budget(base_config(), "cpu")

    lio_cpu, lio_gpu = lio_keyframes.get_config("cpu"), lio_keyframes.get_config("gpu")
    assert (lio_cpu.train.field_lr_init, lio_cpu.train.field_lr_final) == pytest.approx(
        (4 * config.train.field_lr_init, 4 * config.train.field_lr_final))
    gpu = apply_budget(base_config(), "gpu")
    assert (lio_gpu.train.field_lr_init, lio_gpu.train.field_lr_final) == (gpu.train.field_lr_init,
                                                                            gpu.train.field_lr_final)


def test_submap_fields_of_a_long_plan_learn_at_the_cpu_budgets_own_rate():
    """submaps.field_lr_from_steps = (6000, 0.25) on lio_keyframes' cpu budget: the submap fields learn at 4x the
    cpu budget's rate below 6000 planned steps and at the budget's own from 6000 on, whether the steps are asked for
    or a compressed plan's; one cube keeps 4x at any steps."""
    from neld_jax.config import apply_budget, base_config
    from neld_jax.train import make_schedules, with_steps
    from configs import lio_keyframes

    own = apply_budget(base_config(), "cpu").train.field_lr_init
    lio = lio_keyframes.get_config("cpu")
    assert tuple(lio.submaps.field_lr_from_steps) == (6000, 0.25)
    for steps, times in ((1500, 4.0), (5999, 4.0), (6000, 1.0), (30_000, 1.0)):
        planned = with_steps(lio, steps)
        schedules = submap_train.submap_schedules(planned)
        assert float(schedules.field_lr(0)) == pytest.approx(times * own, rel=1e-6)
        # the decay keeps its shape (final / init = train.field_lr_final / _init) over the planned steps
        assert float(schedules.field_lr(steps) / schedules.field_lr(0)) == pytest.approx(
            lio.train.field_lr_final / lio.train.field_lr_init, rel=1e-4)
        assert float(make_schedules(planned).field_lr(0)) == pytest.approx(4.0 * own, rel=1e-6)  # one cube
    assert submap_train.submap_field_lr_factor(base_config()) == 1.0  # (): train.field_lr_* as they are
    for bad in ((6000,), (0, 0.25), (6000, 0.0)):
        lio.submaps.field_lr_from_steps = bad
        with pytest.raises(ConfigError, match="submaps.field_lr_from_steps"):
            submap_train.submap_field_lr_factor(lio)


def test_run_with_submaps_writes_the_single_cube_outputs_within_its_time(tmp_path, monkeypatch):
    """A run whose submaps are switched on: one pose per input scan, one raw and one rendered map (resume with
    sharded state is checked in test_sharded_step_shared_scan_and_resume_on_8_devices). On a fake training clock (1 s
    a step, 5 s a compile) its 100 steps do not fit in train.max_minutes=1.5: the submaps' loop trains a shorter
    plan whole, and metrics.json and config.json say which (the rendered map uses that plan's window)."""
    import json

    from conftest import fake_training_clock, make_tiny_config
    from neld_jax import run
    from neld_jax.data.poses import read_tum

    fake_training_clock(monkeypatch)
    cfg = make_tiny_config(str(tmp_path / "run"), steps=100)
    cfg.data.synthetic.num_scans = 5
    cfg.sampling.coarse_stages, cfg.sampling.fine_stages = (8,), (4,)  # one stage
    cfg.train.fixed_scans, cfg.train.anchor_scan = (), 0
    cfg.train.log_every, cfg.train.checkpoint_every, cfg.train.max_minutes = 10, 0, 1.5
    cfg.submaps.enabled, cfg.submaps.keyframes, cfg.submaps.overlap = "on", 3, 1
    # The map's time limit, already over after the first of its parts: every submap renders that quarter of
    # the rays (a uniform sample), and the run says how many it rendered.
    cfg.mapping.max_seconds = 1e-9
    summary = run.run(cfg, progress=False)
    assert summary["submaps"] == 2 and not summary["stopped_early"]
    assert summary["map_rays_rendered"] == len(np.array_split(np.arange(summary["map_rays"]), 4)[0])
    assert 30 <= summary["schedule_steps"] < 100 and summary["steps"] == summary["schedule_steps"]
    assert json.loads((tmp_path / "run" / "config.json").read_text())["train"]["steps"] == summary["schedule_steps"]
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
    from neld_jax.data.synthetic import make_sequence

    seq = make_sequence({"route": "courtyards", "route_length_m": 600.0, "num_scans": 100, "num_beams": 4,
                         "num_columns": 90, "max_range_m": 30.0, "gt_map_points": 0})
    steps = np.linalg.norm(np.diff(seq.gt_poses[:, :3, 3], axis=0), axis=1)
    assert np.allclose(steps, 6.0, atol=0.1)  # 600 m in 100 even steps (the loop closes: 99 steps + one back)
    assert np.linalg.norm(seq.gt_poses[0, :3, 3] - seq.gt_poses[-1, :3, 3]) == pytest.approx(6.0, abs=0.1)
    assert min(len(s) for s in seq.scans) > 50  # walls, buildings and ground within 30 m everywhere
    config = get_config("cpu")
    config.data.max_range_m = 30.0
    norm = fit_normalization(seq.scans, seq.poses, config.data.normalization_margin)
    plan = submaps.plan_from_config(seq, norm, config)
    assert plan is not None and plan.num_submaps >= 5
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


def test_kept_scale_for_right_corrections_removes_the_first_order_scale_change():
    """train.keep_trajectory_scale with the start's rotations (the submaps' body-frame corrections, applied as
    T_start @ Exp((rho / s_ref, omega)) in metres): the projected step changes the trajectory's scale only at second order,
    the raw one at first order; a step already off the mode passes unchanged."""
    from neld_jax import train

    rng = np.random.default_rng(4)
    S, ref_scale = 8, 0.05  # rho in units of 1 / 0.05 = 20 m: the unit does not change the constraint's direction
    T = np.tile(np.eye(4), (S, 1, 1))
    T[:, :3, :3] = Rotation.random(S, random_state=5).as_matrix()  # far from the identity: R_s matters
    T[:, :3, 3] = rng.normal(0, 10, (S, 3)) + [300.0, -120.0, 15.0]  # world metres, centroid far from the origin
    movable = np.ones(S, bool)
    movable[0] = False  # a fixed scan: its row is zero and stays so
    u = rng.normal(size=(S, 6)) * [1.0, 1.0, 1.0, 0.05, 0.05, 0.05]
    u[0] = 0.0
    u[:, :3] += 0.5 * movable[:, None] * np.einsum("sji,sj->si", T[:, :3, :3], T[:, :3, 3] - T[:, :3, 3].mean(0))
    tx = train.keep_trajectory_scale(T[:, :3, 3], movable, T[:, :3, :3])

    def project(update):
        return np.asarray(tx.update(jnp.asarray(update, jnp.float32), tx.init(None))[0], np.float64)

    kept = project(u)
    np.testing.assert_array_equal(kept[:, 3:], np.asarray(u[:, 3:], np.float32))  # rotations untouched
    np.testing.assert_array_equal(kept[0], 0.0)

    def scale_change(xi, h):
        return similarity_scale(submaps.global_poses(T, h * xi, ref_scale), T)

    for h in (1e-3, 1e-4):  # steps of about 15 cm and 1.5 cm, the scans 17 m from their centroid on average
        free_h, kept_h = scale_change(u, h), scale_change(kept, h)
        assert abs(free_h) > 1e-4 * h / 1e-3  # first order: the raw step scales the route
        assert abs(kept_h) < 1e-2 * abs(free_h)
    # second order: a tenth of the step, a hundredth of the (already tiny) scale change
    assert abs(scale_change(kept, 1e-4)) < 0.02 * abs(scale_change(kept, 1e-3))
    assert abs(scale_change(u, 1e-4)) > 0.05 * abs(scale_change(u, 1e-3))
    # the single cube's left-correction direction does not remove it: the rotations R_s matter
    left = train.keep_trajectory_scale(T[:, :3, 3], movable)
    wrong = np.asarray(left.update(jnp.asarray(u, jnp.float32), left.init(None))[0], np.float64)
    assert abs(scale_change(wrong, 1e-3)) > 0.1 * abs(scale_change(u, 1e-3))
    # off the mode already: unchanged (rotations alone exactly, any a-orthogonal step to float32 round-off)
    a_rho, a_omega = train.scale_direction(T[:, :3, 3], movable, T[:, :3, :3])
    np.testing.assert_array_equal(a_omega, 0.0)
    rotations_only = np.concatenate([np.zeros((S, 3)), u[:, 3:]], axis=1)
    np.testing.assert_array_equal(project(rotations_only), np.asarray(rotations_only, np.float32))
    orthogonal = u - (np.sum(a_rho * u[:, :3]) / np.sum(a_rho * a_rho)) * np.pad(a_rho, ((0, 0), (0, 3)))
    np.testing.assert_allclose(project(orthogonal), orthogonal, rtol=0, atol=1e-6 * np.abs(orthogonal).max())
    np.testing.assert_allclose(kept, orthogonal, rtol=0, atol=1e-6 * np.abs(orthogonal).max())


def _small_submap_setup(keep, start_poses=True, steps=12):
    """A tiny plan (9 keyframes in windows of 3 sharing 1, 4 submaps) of the sphere scene moved far from the
    origin, poses moving from step 0, scan 0 fixed."""
    from conftest import make_tiny_config

    cfg = make_tiny_config("", steps=steps)
    cfg.train.fixed_scans = (0,)
    cfg.train.c2f_end_fraction = 0.0  # poses move from step 0
    cfg.train.log_every, cfg.train.checkpoint_every = steps, 0
    cfg.sampling.coarse_stages, cfg.sampling.fine_stages = (8,), (4,)
    cfg.train.keep_start_scale = keep
    num_scans = 9
    rays_np, T = sphere_scene_rays(num_scans, 48, seed=0)
    T[:, :3, 3] = 10.0 * T[:, :3, 3] + [40.0, -25.0, 3.0]  # a 6 m spread, in metres, far from the origin
    rays_np = dataclasses.replace(rays_np, ranges=10.0 * rays_np.ranges)  # the scene scaled with the poses
    scans = [rays_np.directions[rays_np.scan_index == s] * rays_np.ranges[rays_np.scan_index == s, None]
             for s in range(num_scans)]
    plan = submaps.plan_submaps(scans, T, 3, 1, 0.9)
    rays, frames = submap_train.from_arrays(submaps.submap_arrays(plan, rays_np, T))
    setup = submap_train.create_submap_state(cfg, num_scans, plan.num_submaps,
                                             start_poses=T if start_poses else None)
    return cfg, setup, rays, frames, plan, T


def test_kept_scale_holds_while_the_submaps_train():
    """The submaps' step with train.keep_start_scale: the learned pose rows have no component along the
    right-correction scale mode (a . xi = 0, a_s = [R_s^T (p_s - c), 0] from the world start poses) to float32
    round-off; the free run's have one."""
    from neld_jax import train

    def trained(keep):
        cfg, setup, rays, frames, plan, T = _small_submap_setup(keep)
        state, _ = setup.chunk_fn(setup.state, rays, frames, setup.sampler(0), num_steps=6)
        return np.asarray(state.params["poses"], np.float64), T

    (kept, T), (free, _) = trained(True), trained(False)
    a_rho, _ = train.scale_direction(T[:, :3, 3], np.arange(len(T)) != 0, T[:, :3, :3])

    def relative_scale_change(xi):  # the cosine between the translation rows and the mode
        return abs(np.sum(a_rho * xi[:, :3])) / (np.linalg.norm(a_rho) * np.linalg.norm(xi[:, :3]))

    assert np.abs(kept[1:, :3]).max() > 1e-4 and np.all(kept[0] == 0)  # the poses moved; the fixed scan did not
    assert relative_scale_change(kept) < 1e-5
    assert relative_scale_change(free) > 1e-3


def test_kept_scale_needs_the_submaps_start_poses_and_a_new_plan_keeps_them(monkeypatch):
    """create_submap_state refuses train.keep_start_scale without the start poses, and fit_submaps' replan (here
    a resumed run's shorter plan) rebuilds the optimiser from the setup's start poses."""
    with pytest.raises(ValueError, match="keep_start_scale"):
        _small_submap_setup(True, start_poses=False)
    cfg, setup, rays, frames, plan, T = _small_submap_setup(True)
    assert setup.start_poses is T

    class Replanned(Exception):
        pass

    def replan(config, num_scans, num_submaps, mesh=None, start_poses=None):
        assert int(config.train.steps) == 6 and start_poses is T
        raise Replanned  # before anything compiles

    monkeypatch.setattr(submap_train, "create_submap_state", replan)
    with pytest.raises(Replanned):  # run_chunks replans to the 6 steps the history holds, before the first step
        submap_train.fit_submaps(cfg, setup, rays, frames, plan.ref_scale, progress=False,
                                 history=[{"step": 0, "total_steps": 6}], max_seconds=0.0)

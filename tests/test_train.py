"""The jitted train step: pose freezing before k*, the gauge, compiles per stage, schedules."""

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from neld_jax import train
from neld_jax.data.rays import sphere_scene_rays
from neld_jax.errors import ConfigError
from neld_jax.field import DensityField
from neld_jax.lie import se3_exp_float64

from conftest import fake_training_clock, make_tiny_config, similarity_scale


def _random_rays(num_scans=3, per_scan=64, seed=0):
    """Rays of `num_scans` scans whose sensors sit inside the cube, looking at a sphere of radius 0.8."""
    rays, T = sphere_scene_rays(num_scans, per_scan, seed, spread=0.2)
    return train.device_rays(rays), jnp.asarray(T, jnp.float32)


def _assert_trees_equal(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_poses_frozen_before_k_star_then_move_and_scan0_fixed(monkeypatch):
    config = make_tiny_config(steps=20)
    # The step's Python body runs only while jax traces it: count its calls of render_rays to count compiles.
    traces = []
    render_rays = train.render_rays
    monkeypatch.setattr(train, "render_rays", lambda *args, **kwargs: traces.append(1) or render_rays(*args, **kwargs))
    setup = train.create_train_state(config, 3, 1.0)
    schedules, state, step_fn = setup.schedules, setup.state, setup.step_fn
    # pos_freqs 8, c2f over 10 steps: frequency 6 starts at step ceil(6/8*10) = 8.
    assert schedules.pose_start_step == 8
    rays, T_init = _random_rays()
    poses_per_step = []
    stages_seen = set()
    for step in range(config.train.steps):
        stages_seen.add(schedules.samples(step))
        state, metrics = step_fn(state, rays, T_init, setup.sampler(step))
        assert np.isfinite(float(metrics["loss"]))
        poses_per_step.append(np.asarray(state.params["poses"]))
    poses_per_step = np.stack(poses_per_step)  # [steps, S, 6]; entry i is after step i+1
    # Updates at steps 0..7 are exactly zero; the first move happens in step 8 (entry 8).
    assert np.all(poses_per_step[:8] == 0.0)
    assert np.abs(poses_per_step[-1, 1:]).max() > 0.0
    assert np.all(poses_per_step[:, 0] == 0.0), "the gauge-fixed scan 0 moved"
    # Two sample-count stages -> two traces, however many steps.
    assert len(stages_seen) == 2
    assert len(traces) == 2
    assert int(state.step) == config.train.steps


def test_initial_density_is_set_from_the_command_line():
    """--config.model.initial_density reaches the field that training builds (and the untrained field's output)."""
    from absl import flags
    from ml_collections import config_flags

    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    argv = ["train.py", f"--config={os.path.join(repo, 'configs', 'demo.py')}", "--config.model.initial_density=0.5",
            "--config.model.width=16", "--config.model.depth=2", "--config.model.skip_layers=(1,)"]
    flag_values = flags.FlagValues()  # as bin/train.py parses them (neld_jax.cli), without the global flags
    config_flags.DEFINE_config_file("config", None, "", flag_values=flag_values, lock_config=True, sys_argv=argv)
    flag_values(argv)
    config = flag_values.config
    setup = train.create_train_state(config, 2, 1.0)
    assert setup.field.initial_density == 0.5 and setup.field.width == 16 and setup.field.skip_layers == (1,)
    points = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (64, 3)), jnp.float32)
    view = points / jnp.linalg.norm(points, axis=1, keepdims=True)
    sigma = setup.field.apply({"params": setup.state.params["field"]}, points, view)
    np.testing.assert_allclose(np.asarray(sigma), 0.5, atol=0.05)
    # The default is the module's own.
    assert train.make_field(make_tiny_config()).initial_density == DensityField.initial_density == 0.1


def test_fit_and_initial_state_start_from_the_builders_state():
    config = make_tiny_config(steps=0)
    setup = train.create_train_state(config, 3, 1.0)
    rays, T_init = _random_rays()
    fitted = train.fit(config, rays, T_init, scale=1.0, progress=False).state  # no step: the start itself
    for state in (fitted, train.initial_state(config, 3, 1.0)):
        _assert_trees_equal(state.params, setup.state.params)
        _assert_trees_equal(state.opt_state, setup.state.opt_state)
        np.testing.assert_array_equal(jax.random.key_data(state.key), jax.random.key_data(setup.state.key))
    assert setup.field == train.make_field(config)  # hashable and equal: one static argument, one compile
    assert hash(setup.field) == hash(train.make_field(config))
    assert setup.sampler(0) == train.sampler_settings(config, 1.0, *setup.schedules.samples(0))
    assert train.LossSettings.from_config(config.loss) == train.LossSettings()  # the config's defaults


@functools.lru_cache(maxsize=None)
def _sphere_fit():
    """(config, rays, T_init, FitResult) of a field-only fit on the sphere scene, shared by two tests."""
    config = make_tiny_config(steps=300)
    config.model.width, config.model.depth = 32, 2
    config.train.batch_rays = 128
    config.train.field_lr_init, config.train.field_lr_final = 5e-3, 1e-3
    config.train.fixed_scans = (0, 1, 2)  # field only
    rays, T_init = _random_rays()
    return config, rays, T_init, train.fit(config, rays, T_init, scale=1.0, progress=False)


def test_field_learns_ranges():
    """A few hundred steps on the sphere scene bring the range error well below its initial value."""
    _, _, _, result = _sphere_fit()
    first, last = result.history[0]["range_l1_fine"], result.history[-1]["range_l1_fine"]
    assert last < 0.5 * first, (first, last)
    # The median residual is logged beside the mean (scale 1: normalised units are metres here) and falls too.
    median_first, median_last = (result.history[i]["range_residual_median_m"] for i in (0, -1))
    assert 0 < median_last < 0.5 * median_first, (median_first, median_last)
    assert np.all(np.asarray(result.state.params["poses"]) == 0.0)


def test_schedules_follow_the_paper_at_full_size():
    from neld_jax.config import base_config

    s = train.make_schedules(base_config())
    assert s.total_steps == 160_000
    assert s.c2f_end_step == 120_000
    assert s.pose_start_step == 48_000  # frequency 6 of 15 at 6/15 of 120k
    assert s.samples(0) == (32, 16) and s.samples(119_999) == (48, 24) and s.samples(120_000) == (64, 32)
    assert float(s.alpha(60_000)) == pytest.approx(7.5)
    assert float(s.field_lr(0)) == pytest.approx(5e-5) and float(s.field_lr(160_000)) == pytest.approx(2e-5)
    assert float(s.pose_lr_trans(47_999)) == 0.0 and float(s.pose_lr_trans(48_000)) == pytest.approx(5e-5)


def test_fixed_scan_out_of_range_is_an_error():
    config = make_tiny_config()
    config.train.fixed_scans = (5,)
    with pytest.raises(ValueError, match="fixed_scans names scan 5"):
        train.make_optimizer(config, train.make_schedules(config), 3)


def test_pose_prior_pulls_corrections_back_to_their_start_and_is_off_at_zero():
    config = make_tiny_config()
    config.train.fixed_scans = ()
    schedules = train.make_schedules(config)
    xi = jnp.asarray([[0.01, -0.02, 0.0, 0.0, 0.003, -0.001], [0.0] * 6])
    no_data = jnp.zeros_like(xi)  # the data says nothing: only the prior may move a pose
    step = schedules.pose_start_step  # the rate is 0 before the poses start

    def update(weight, rot_factor=1.0):
        config.train.pose_prior_weight = weight
        config.train.pose_prior_rot_factor = rot_factor
        tx = train.pose_transform(config, schedules, 2)
        state = tx.init(xi)
        for _ in range(step + 1):
            updates, state = tx.update(no_data, state, xi)
        return np.asarray(updates)

    pulled = update(10.0)
    moved = xi[0] != 0
    assert np.all(np.sign(pulled[0][moved]) == -np.sign(xi[0][moved]))  # toward zero, each component
    assert np.all(pulled[0][~moved] == 0) and np.all(pulled[1] == 0)  # a pose at its start stays there
    assert np.all(update(0.0) == 0)
    # pose_prior_rot_factor weighs the rotation columns' pull alone: at 0 only the translations are pulled
    translations_only = update(10.0, rot_factor=0.0)
    np.testing.assert_array_equal(translations_only[:, :3], pulled[:, :3])
    assert np.all(translations_only[:, 3:] == 0)


def test_pose_prior_weighs_translation_and_rotation_columns_and_equals_decayed_weights_at_one_weight():
    xi = jnp.asarray([[0.01, -0.02, 0.004, 0.003, -0.001, 0.002], [0.0, 0.5, 0.0, -0.2, 0.0, 0.1]])
    grads = jnp.full_like(xi, 0.25)
    prior = train.pose_prior(10.0, 2.5)
    updates, _ = prior.update(grads, prior.init(xi), xi)
    np.testing.assert_allclose(updates[:, :3], 0.25 + 10.0 * xi[:, :3], rtol=1e-6)
    np.testing.assert_allclose(updates[:, 3:], 0.25 + 2.5 * xi[:, 3:], rtol=1e-6)
    # one weight: optax.add_decayed_weights's update and state (what checkpoints written before this hold)
    same, decayed = train.pose_prior(10.0, 10.0), optax.add_decayed_weights(10.0)
    np.testing.assert_array_equal(same.update(grads, same.init(xi), xi)[0],
                                  decayed.update(grads, decayed.init(xi), xi)[0])
    assert jax.tree.structure(same.init(xi)) == jax.tree.structure(decayed.init(xi))


def test_keeping_the_start_scale_takes_only_the_scale_mode_out_of_the_pose_steps():
    config = make_tiny_config()
    config.train.fixed_scans = (0,)
    schedules = train.make_schedules(config)
    rng = np.random.default_rng(0)
    T_init = np.tile(np.eye(4), (5, 1, 1))
    T_init[:, :3, 3] = rng.normal(size=(5, 3)) + [0.0, 0.0, 0.5]  # centroid away from the origin
    grads = rng.normal(size=(5, 6)) * 1e-3
    grads[:, :3] -= 0.5 * (T_init[:, :3, 3] - T_init[:, :3, 3].mean(0))  # the data pushes the route to grow
    xi = jnp.zeros((5, 6))

    def step(start_positions):
        config.train.keep_start_scale = start_positions is not None
        tx = train.pose_transform(config, schedules, 5, start_positions)
        state = tx.init(xi)
        for _ in range(schedules.pose_start_step + 1):
            updates, state = tx.update(jnp.asarray(grads), state, xi)
        return np.asarray(updates)

    def route_scale(xi):  # of the positions of exp(xi) T_init against T_init's, minus 1
        return similarity_scale(se3_exp_float64(xi) @ T_init, T_init)

    free, kept = step(None), step(T_init[:, :3, 3])
    lr = 1e-4 / max(np.abs(free).max(), 1e-12)  # steps of 1e-4, so that second-order terms stay below 1e-7
    assert abs(route_scale(lr * free)) > 1e-5  # the free step scales the route
    assert abs(route_scale(lr * kept)) < 1e-3 * abs(route_scale(lr * free))  # kept: not
    np.testing.assert_array_equal(kept[0], 0)  # the fixed scan
    np.testing.assert_allclose(kept[:, 3:], free[:, 3:])  # rotations untouched
    centred = T_init[1:, :3, 3] - T_init[:, :3, 3].mean(0)
    eps = (kept[1:, :3] - free[1:, :3]) / centred  # what changed: eps * (p_s - c) on the translations alone
    np.testing.assert_allclose(eps, eps[0, 0], rtol=1e-3)
    # a run builds it from its initial poses, and its state has the structure of initial_state's (the checkpoint
    # template, built without the poses)
    config.train.keep_start_scale = True
    setup = train.create_train_state(config, 5, 1.0, T_init[:, :3, 3])
    assert jax.tree.structure(setup.state) == jax.tree.structure(train.initial_state(config, 5, 1.0))
    with pytest.raises(ValueError, match="keep_start_scale"):
        train.create_train_state(config, 5, 1.0)


def test_the_kept_scale_holds_while_training():
    # fit builds the constraint from its initial poses: the trained corrections have no component along the scale
    # mode (a . xi = 0, train.keep_trajectory_scale's a), which the free run's have
    rays, T_init = _random_rays()
    p = np.asarray(T_init, np.float64)[:, :3, 3]
    c = p.mean(axis=0)

    def scale_change(xi):
        return np.sum((p - c) * xi[:, :3]) + np.sum(np.cross(c, p) * xi[:, 3:])

    def trained(keep):
        config = make_tiny_config(steps=20)  # the poses move from step 8
        config.train.fixed_scans = ()
        config.train.keep_start_scale = keep
        return np.asarray(train.fit(config, rays, T_init, scale=1.0, progress=False).state.params["poses"])

    free, kept = trained(False), trained(True)
    assert np.abs(kept[:, :3]).max() > 1e-4
    assert abs(scale_change(kept)) < 1e-3 * abs(scale_change(free))


def test_unknown_budget_is_a_config_error():
    from neld_jax.config import apply_budget, base_config

    with pytest.raises(ConfigError, match="unknown budget"):
        apply_budget(base_config(), "tpu")


def test_no_positional_frequencies_trains():
    """model.pos_freqs=0 (the encoding is then x alone): no frequency to wait for, poses start at the warm-up."""
    config = make_tiny_config(steps=2)
    config.model.pos_freqs = 0
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    assert train.make_schedules(config).pose_start_step == 0
    config.train.pose_warmup_steps = 1
    assert train.make_schedules(config).pose_start_step == 1
    rays, T_init = _random_rays()
    result = train.fit(config, rays, T_init, scale=1.0, progress=False)
    assert int(result.state.step) == 2 and np.isfinite(result.history[-1]["loss"])


def test_wall_clock_guard_stops_at_a_chunk_end_and_max_seconds_overrides_the_config(caplog):
    """The guard moves at chunk ends: a limit already spent stops after the first chunk, stopped_early says so, and
    the state is the first chunk's; max_seconds=0 (a caller's "no limit") runs every step whatever the config says."""
    config = make_tiny_config(steps=6)
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    config.train.log_every, config.train.checkpoint_every = 2, 0
    config.train.max_minutes = 1e-9
    rays, T_init = _random_rays()
    with caplog.at_level("WARNING", logger="neld_jax.train"):
        stopped = train.fit(config, rays, T_init, scale=1.0, progress=False)
    assert stopped.stopped_early and int(stopped.state.step) == 2
    assert "stopping at step 2 of 6" in caplog.text
    unlimited = train.fit(config, rays, T_init, scale=1.0, progress=False, max_seconds=0.0)
    assert not unlimited.stopped_early and int(unlimited.state.step) == 6
    config.train.max_minutes = 0.0
    narrowed = train.fit(config, rays, T_init, scale=1.0, progress=False, max_seconds=1e-9)
    assert narrowed.stopped_early and int(narrowed.state.step) == 2


def test_steps_that_fit():
    assert train.steps_that_fit(20, 100, 100.0, 1.0, 25) == 100  # 80 steps in 100 s fit
    assert train.steps_that_fit(20, 100, 30.0, 1.0, 25) == 47  # 27 more in 30 s, 10 % in hand
    assert train.steps_that_fit(20, 100, 2.0, 1.0, 25) == 25  # never below min_total
    assert train.steps_that_fit(20, 100, 30.0, 0.0, 25) == 100  # no rate: no plan


def test_the_guard_compresses_the_schedule_and_a_resumed_run_keeps_the_plan(monkeypatch):
    """On a fake clock (1 s a step, 5 s to compile each plan's chunk) 100 planned steps cannot fit in 60 s: after
    the second chunk (35 s left, three compiles of 5 s kept in hand) the schedule is compressed to the 38 that fit,
    and it runs whole (the coarse-to-fine window ends, the guard does not cut it). A run resumed from that history
    keeps 38."""
    clock = fake_training_clock(monkeypatch)
    config = make_tiny_config(steps=100)
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    config.train.log_every, config.train.checkpoint_every, config.train.max_minutes = 10, 0, 1.0
    rays, T_init = _random_rays()
    result = train.fit(config, rays, T_init, scale=1.0, progress=False)
    assert result.total_steps == 38 and int(result.state.step) == 38 and not result.stopped_early
    assert [h["total_steps"] for h in result.history[:2]] == [100, 100] and result.history[-1]["total_steps"] == 38
    assert result.history[-1]["alpha"] == config.model.pos_freqs  # the compressed window ended
    assert clock[0] <= 60.0
    config.train.max_minutes = 0.0
    resumed = train.fit(config, rays, T_init, scale=1.0, progress=False, history=[{"step": 0, "total_steps": 38}])
    assert resumed.total_steps == 38 and int(resumed.state.step) == 38


def test_fit_logs_why_poses_start_and_reports_the_translation_of_exp_xi(caplog):
    config = make_tiny_config(steps=4)
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    config.train.fixed_scans = (0, 1, 2)  # the corrections below stay as set
    # k* = 6 of 8 starts at ceil(6/8 * 2) = 2; the warm-up holds the poses until step 3.
    config.train.pose_warmup_steps = 3
    rays, T_init = _random_rays()
    scale = 0.5
    xi = np.array([[0.2, -0.1, 0.3, 0.0, 0.0, 1.2], [0.0, 0.4, 0.0, 0.9, 0.0, 0.0], [0.1, 0.1, 0.1, 0.3, -0.5, 0.7]],
                  np.float32)
    state = train.initial_state(config, 3, scale)
    state = state.replace(params={**state.params, "poses": jnp.asarray(xi)})
    with caplog.at_level("INFO", logger="neld_jax.train"):
        result = train.fit(config, rays, T_init, scale, state=state, progress=False)
    assert "step 3: poses start moving (train.pose_warmup_steps" in caplog.text
    assert "frequency 6 active" not in caplog.text
    # The translation of exp(xi) is V(omega) rho, by Rodrigues' formula written out here.
    expected = []
    for rho, omega in zip(xi[:, :3].astype(np.float64), xi[:, 3:].astype(np.float64)):
        theta = np.linalg.norm(omega)
        K = np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]])
        V = np.eye(3) + (1 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * K @ K
        expected.append(np.linalg.norm(V @ rho))
    expected_m = np.mean(expected) / scale
    assert abs(np.mean(np.linalg.norm(xi[:, :3], axis=1)) / scale - expected_m) > 0.01  # |rho| would be wrong
    assert result.history[-1]["pose_trans_mean_m"] == pytest.approx(expected_m, rel=1e-5)
    assert np.all(np.asarray(result.state.params["poses"]) == xi)
    k_star_config = make_tiny_config(steps=20)  # here k* sets the start (step 8)
    assert "frequency 6 active" in train.pose_start_message(k_star_config, train.make_schedules(k_star_config))


def test_per_scan_batches_draw_whole_groups_of_one_scan():
    from neld_jax.data.rays import RaySet

    scan_index = np.repeat(np.arange(5), [3, 50, 7, 1, 20]).astype(np.int32)
    rayset = RaySet(np.tile([[1.0, 0, 0]], (len(scan_index), 1)).astype(np.float32),
                    np.arange(len(scan_index), dtype=np.float32), scan_index)
    rays = train.device_rays(rayset)
    np.testing.assert_array_equal(rays.scan_start, [0, 3, 53, 60, 61])
    np.testing.assert_array_equal(rays.scan_count, [3, 50, 7, 1, 20])
    idx = np.asarray(jax.jit(train.sample_batch, static_argnums=(2, 3))(jax.random.PRNGKey(0), rays, 64, 4))
    groups = scan_index[idx].reshape(4, 16)
    assert np.all(groups == groups[:, :1])  # each group of 16 rays comes from one scan
    assert idx.min() >= 0 and idx.max() < len(scan_index)
    uniform = np.asarray(train.sample_batch(jax.random.PRNGKey(0), rays, 64, 0))
    assert len(np.unique(scan_index[uniform])) > 1
    with pytest.raises(ValueError, match="grouped by scan"):
        train.device_rays(RaySet(rayset.directions[:3], rayset.ranges[:3], np.array([1, 0, 1], np.int32)))


def test_chunks_end_at_log_steps_and_never_straddle_stages_pose_start_or_checkpoints():
    config = make_tiny_config(steps=20)  # stages start at steps 0 and 10; poses start at step 8
    schedules = train.make_schedules(config)
    assert schedules.stage_starts == (0, 10) and schedules.pose_start_step == 8
    bounds = train.chunk_bounds(0, 20, 4, 6, schedules)  # log every 4, checkpoint every 6
    assert bounds == [(0, 4), (4, 6), (6, 8), (8, 10), (10, 12), (12, 16), (16, 18), (18, 20)]
    assert train.chunk_bounds(0, 20, 100, 0, schedules) == [(0, 8), (8, 10), (10, 20)]
    # A run resumed at a checkpoint cuts the same chunks from there on.
    assert train.chunk_bounds(12, 20, 4, 6, schedules) == bounds[-3:]
    assert train.chunk_bounds(20, 20, 4, 6, schedules) == []


def test_fit_in_chunks_equals_single_steps():
    """fit's fused loop (chunks of K = log_every steps, one lax.scan each) reaches the state of the jitted step
    called once per step, bit for bit on XLA:CPU, and logs that step's metrics at the chunk ends."""
    config = make_tiny_config(steps=10)
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)  # one stage, poses move from step
    config.train.pose_start_freq = 0  # 0 on, no checkpoints: every chunk is 5 steps, one compile
    config.train.checkpoint_every, config.train.log_every = 0, 5
    rays, T_init = _random_rays()
    fitted = train.fit(config, rays, T_init, scale=1.0, progress=False)
    assert [h["step"] for h in fitted.history] == [5, 10]
    setup = train.create_train_state(config, 3, 1.0)
    state, losses = setup.state, []
    for step in range(10):
        state, metrics = setup.step_fn(state, rays, T_init, setup.sampler(step))
        losses.append(float(metrics["loss"]))
    assert int(fitted.state.step) == int(state.step) == 10
    assert np.abs(np.asarray(state.params["poses"])).max() > 0  # the poses moved inside the chunks too
    # Bit-identical on XLA:CPU (measured); a backend that fuses the loop body differently may round differently.
    _assert_trees_equal((fitted.state.params, fitted.state.opt_state), (state.params, state.opt_state))
    np.testing.assert_array_equal(jax.random.key_data(fitted.state.key), jax.random.key_data(state.key))
    assert [h["loss"] for h in fitted.history] == [losses[4], losses[9]]  # the last step of each chunk
    assert set(fitted.history[0]) >= set(metrics) | {"step", "range_err_m", "range_residual_median_m",
                                                      "pose_trans_mean_m", "elapsed_s"}


def test_bfloat16_matmuls_render_depth_close_to_float32_and_give_gradients():
    """model.matmul_dtype=bfloat16 on the trained sphere field (float32 parameters): rendered depths within ~1%
    of float32's, and finite parameter gradients through the bfloat16 matmuls (the training path)."""
    from neld_jax.model import render_rays, scan_poses, world_rays

    config, rays, T_init, result = _sphere_fit()
    params = result.state.params
    field32 = train.make_field(config)
    field16 = field32.clone(matmul_dtype="bfloat16")
    assert field32.matmul_dtype == "float32"
    sampler = train.sampler_settings(config, 1.0, 16, 8)
    T = scan_poses(params["poses"], T_init)[rays.scan_index]
    origins, directions = world_rays(T, rays.directions)
    ranges = np.asarray(rays.ranges)

    def depth_loss(field_params, field):
        depth = render_rays(field_params, field, sampler, origins, directions, jnp.asarray(8.0)).fine.depth
        return jnp.mean(jnp.abs(depth - rays.ranges)), depth

    depth32 = np.asarray(jax.jit(lambda p: depth_loss(p, field32)[1])(params["field"]))
    (_, depth16), grads = jax.jit(jax.value_and_grad(lambda p: depth_loss(p, field16), has_aux=True))(params["field"])
    depth16 = np.asarray(depth16)
    difference = np.abs(depth16 - depth32)
    assert np.median(difference) < 0.01 * np.median(ranges), np.median(difference)
    assert difference.max() > 0  # the two really ran different matmuls
    assert np.median(np.abs(depth16 - ranges)) < 1.5 * np.median(np.abs(depth32 - ranges)) + 1e-3
    leaves = jax.tree.leaves(grads)
    assert all(g.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(g))) for g in leaves)
    assert max(float(jnp.abs(g).max()) for g in leaves) > 0
    lowered = jax.jit(lambda p: depth_loss(p, field16)[1]).lower(params["field"]).as_text()
    assert "xbf16>" in lowered  # bfloat16 operands

"""The trainer (training.train): one pytree, one optimiser, one step and one loop for one cube and for many. Pose
freezing before k*, the gauge, compiles per stage, schedules, the pose prior and the kept scale, the clock, the fused
loop, and on 8 simulated CPU devices (a subprocess) the sharded step, a shared scan's gradient and a resume."""

import functools
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import fake_training_clock, make_tiny_config, similarity_scale, sphere_plan
from scipy.spatial.transform import Rotation

from neld_jax.config import defaults, with_budget
from neld_jax.errors import ConfigError
from neld_jax.field.model import world_poses
from neld_jax.training import train

HERE = os.path.dirname(os.path.abspath(__file__))


def _trainer(config, plan, T, pose_steps=None, steps=None):
    return train.make_trainer(
        config, len(T), plan.num_submaps, pose_steps or train.PoseSteps.from_config(config), T, steps
    )


def _fit(config, rays, frames, plan, T, pose_steps=None, max_seconds=0.0, **kwargs):
    plan_of = functools.partial(
        train.make_trainer, config, len(T), plan.num_submaps, pose_steps or train.PoseSteps.from_config(config), T
    )
    state = kwargs.pop("state", None) or train.init_state(
        config, plan_of(int(config.train.steps)), len(T), plan.num_submaps
    )
    return train.fit(
        config,
        plan_of,
        train.TrainingData(rays, frames, plan.ref_scale),
        state,
        settings=train.FitSettings(max_seconds, progress=False),
        **kwargs,
    )


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
    rays, frames, plan, T = sphere_plan()
    trainer = _trainer(config, plan, T)
    # pos_freqs 8, c2f over 10 steps: frequency 6 starts at step ceil(6/8*10) = 8.
    assert trainer.schedules.pose_start_step == 8
    state = train.init_state(config, trainer, 3, 1)
    step = jax.jit(trainer.step, static_argnames=("sampler",))
    poses_per_step, stages_seen = [], set()
    for i in range(config.train.steps):
        stages_seen.add(trainer.schedules.samples(i))
        state, metrics = step(state, rays, frames, trainer.sampler(i))
        assert np.isfinite(float(metrics["loss"]))
        poses_per_step.append(np.asarray(state.params["poses"]))
    poses_per_step = np.stack(poses_per_step)  # [steps, S, 6]; entry i is after step i+1
    assert np.all(poses_per_step[:8] == 0.0)  # updates at steps 0..7 are exactly zero
    assert np.abs(poses_per_step[-1, 1:]).max() > 0.0
    assert np.all(poses_per_step[:, 0] == 0.0), "the gauge-fixed scan 0 moved"
    assert len(stages_seen) == 2 and len(traces) == 2  # two sample-count stages, two traces
    assert int(state.step) == config.train.steps


def test_fit_without_steps_is_the_seeded_initial_state():
    config = make_tiny_config(steps=0)
    rays, frames, plan, T = sphere_plan()
    trainer = _trainer(config, plan, T)
    start = train.init_state(config, trainer, 3, 1)
    fitted = _fit(config, rays, frames, plan, T).state  # no step: the start itself
    again = train.init_state(config, _trainer(config, plan, T), 3, 1)
    for state in (fitted, again):
        _assert_trees_equal(state.params, start.params)
        _assert_trees_equal(state.opt_state, start.opt_state)
        np.testing.assert_array_equal(jax.random.key_data(state.key), jax.random.key_data(start.key))
    assert jax.tree.leaves(start.params["fields"])[0].shape[0] == 1  # one cube: the fields' leading axis is 1
    assert trainer.field == train.make_field(config) and hash(trainer.field) == hash(train.make_field(config))
    assert trainer.sampler(0) == train.sampler_settings(config.sampling, *trainer.schedules.samples(0))  # metres
    assert train.loss_settings(config) == train.LossSettings()  # the config's defaults


@functools.lru_cache(maxsize=None)
def _sphere_fit():
    """(config, rays, frames, plan, T, FitResult) of a field-only fit on the sphere scene, shared by two tests."""
    config = make_tiny_config(steps=300)
    config.model.width, config.model.depth = 32, 2
    config.train.batch_rays = 128
    config.train.field_lr_init, config.train.field_lr_final = 5e-3, 1e-3
    config.train.fixed_scans = (0, 1, 2)  # field only
    rays, frames, plan, T = sphere_plan()
    return config, rays, frames, plan, T, _fit(config, rays, frames, plan, T)


def test_field_learns_ranges():
    """A few hundred steps on the sphere scene bring the range error well below its initial value."""
    *_, result = _sphere_fit()
    first, last = result.history[0]["range_l1_fine"], result.history[-1]["range_l1_fine"]
    assert last < 0.5 * first, (first, last)
    # The median residual is logged beside the mean (scale 1: the cube's units are metres here) and falls too.
    median_first, median_last = (result.history[i]["range_residual_median_m"] for i in (0, -1))
    assert 0 < median_last < 0.5 * median_first, (median_first, median_last)
    assert np.all(np.asarray(result.state.params["poses"]) == 0.0)


def test_schedules_follow_the_paper_at_full_size():
    config = defaults()
    s = train.make_schedules(config, train.PoseSteps.from_config(config))
    assert s.total_steps == 160_000 and s.c2f_end_step == 120_000
    assert s.pose_start_step == 48_000  # frequency 6 of 15 at 6/15 of 120k
    assert s.samples(0) == (32, 16) and s.samples(59_999) == (32, 16) and s.samples(60_000) == (48, 24)
    assert s.samples(119_999) == (48, 24) and s.samples(120_000) == (64, 32)
    assert float(s.alpha(60_000)) == pytest.approx(7.5)
    assert float(s.field_lr(0)) == pytest.approx(5e-5) and float(s.field_lr(160_000)) == pytest.approx(2e-5)
    assert float(s.pose_lr_trans(47_999)) == 0.0 and float(s.pose_lr_trans(48_000)) == pytest.approx(5e-5)


def test_fixed_scan_out_of_range_is_an_error():
    config = make_tiny_config()
    config.train.fixed_scans = (5,)
    with pytest.raises(ConfigError, match=r"train.fixed_scans = \(5,\): scan 5 is not one of the 3 keyframes"):
        train.fixed_rows(config.train, 3)


def test_pose_prior_pulls_corrections_back_to_their_start_and_is_off_at_zero():
    config = make_tiny_config()
    xi = jnp.asarray([[0.01, -0.02, 0.0, 0.0, 0.003, -0.001], [0.0] * 6])
    no_data = jnp.zeros_like(xi)  # the data says nothing: only the prior may move a pose

    def update(trans, rot):
        steps = train.PoseSteps((1e-3, 1e-4), (1e-3, 1e-4), trans, rot)
        schedules = train.make_schedules(config, steps)
        tx = train.pose_transform(schedules, steps, np.zeros(2, bool))
        state = tx.init(xi)
        for _ in range(schedules.pose_start_step + 1):  # the rate is 0 before the poses start
            updates, state = tx.update(no_data, state, xi)
        return np.asarray(updates)

    pulled = update(10.0, 10.0)
    moved = xi[0] != 0
    assert np.all(np.sign(pulled[0][moved]) == -np.sign(xi[0][moved]))  # toward zero, each component
    assert np.all(pulled[0][~moved] == 0) and np.all(pulled[1] == 0)  # a pose at its start stays there
    assert np.all(update(0.0, 0.0) == 0)
    translations_only = update(10.0, 0.0)  # the rotation columns' own weight
    np.testing.assert_array_equal(translations_only[:, :3], pulled[:, :3])
    assert np.all(translations_only[:, 3:] == 0)
    prior = train.pose_prior(10.0, 2.5)
    grads = jnp.full_like(xi, 0.25)
    raw, _ = prior.update(grads, prior.init(xi), xi)
    np.testing.assert_allclose(raw[:, :3], 0.25 + 10.0 * xi[:, :3], rtol=1e-6)
    np.testing.assert_allclose(raw[:, 3:], 0.25 + 2.5 * xi[:, 3:], rtol=1e-6)


def test_the_kept_scale_removes_the_first_order_scale_change_of_right_corrections():
    """scale_direction's a_s = [R_s^T (p_s - c), 0] for T_start @ Exp((rho / s_ref, omega)): the projected step
    changes the trajectory's scale only at second order, the raw one at first order; rotations are untouched; a
    fixed row stays 0; a step already off the mode passes unchanged."""
    rng = np.random.default_rng(4)
    S, ref_scale = 8, 0.05  # rho in units of 1 / 0.05 = 20 m: the unit does not change the constraint's direction
    T = np.tile(np.eye(4), (S, 1, 1))
    T[:, :3, :3] = Rotation.random(S, random_state=5).as_matrix()  # far from the identity: R_s matters
    T[:, :3, 3] = rng.normal(0, 10, (S, 3)) + [300.0, -120.0, 15.0]  # world metres, centroid far from the origin
    movable = np.ones(S, bool)
    movable[0] = False
    u = rng.normal(size=(S, 6)) * [1.0, 1.0, 1.0, 0.05, 0.05, 0.05]
    u[0] = 0.0
    u[:, :3] += 0.5 * movable[:, None] * np.einsum("sji,sj->si", T[:, :3, :3], T[:, :3, 3] - T[:, :3, 3].mean(0))
    a = train.scale_direction(T, movable)
    tx = train.keep_off_direction(a)

    def project(update):
        return np.asarray(tx.update(jnp.asarray(update, jnp.float32), tx.init(None))[0], np.float64)

    kept = project(u)
    np.testing.assert_array_equal(kept[:, 3:], np.asarray(u[:, 3:], np.float32))
    np.testing.assert_array_equal(kept[0], 0.0)

    def scale_change(xi, h):
        return similarity_scale(world_poses(T, h * xi, ref_scale), T)

    for h in (1e-3, 1e-4):  # steps of about 15 cm and 1.5 cm, the scans 17 m from their centroid on average
        free_h, kept_h = scale_change(u, h), scale_change(kept, h)
        assert abs(free_h) > 1e-4 * h / 1e-3  # first order: the raw step scales the route
        assert abs(kept_h) < 1e-2 * abs(free_h)
    assert abs(scale_change(kept, 1e-4)) < 0.02 * abs(scale_change(kept, 1e-3))  # second order
    np.testing.assert_array_equal(a[:, 3:], 0.0)
    orthogonal = u - (np.sum(a * u) / np.sum(a * a)) * a
    np.testing.assert_allclose(project(orthogonal), orthogonal, rtol=0, atol=1e-6 * np.abs(orthogonal).max())


@pytest.mark.parametrize("window", [0, 3])
def test_the_kept_scale_holds_while_training(window):
    """fit with pose_steps.keep_scale, one cube and windows: the learned rows have no component along the scale mode
    (a . xi = 0) to float32 round-off; the free run's have one."""
    config = make_tiny_config(steps=12)
    config.train.c2f_end_fraction = 0.0  # the poses move from step 0
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    config.train.log_every, config.train.checkpoint_every = 12, 0
    rays, frames, plan, T = sphere_plan(num_scans=7, per_scan=48, window=window)
    a = train.scale_direction(T, np.arange(len(T)) != 0)

    def trained(keep):
        steps = train.PoseSteps((1e-3, 1e-4), (1e-3, 1e-4), keep_scale=keep)
        return np.asarray(_fit(config, rays, frames, plan, T, steps).state.params["poses"], np.float64)

    kept, free = trained(True), trained(False)

    def cosine(xi):
        return abs(np.sum(a * xi)) / (np.linalg.norm(a) * np.linalg.norm(xi[:, :3]))

    assert np.abs(kept[1:, :3]).max() > 1e-4 and np.all(kept[0] == 0)
    assert cosine(kept) < 1e-5 and cosine(free) > 1e-3
    with pytest.raises(ValueError, match="start poses"):
        train.make_trainer(config, len(T), plan.num_submaps, train.PoseSteps(keep_scale=True))


def test_no_positional_frequencies_trains():
    """model.pos_freqs=0 (the encoding is then x alone): no frequency to wait for, the poses move from step 0."""
    config = make_tiny_config(steps=2)
    config.model.pos_freqs = 0
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    assert train.make_schedules(config, train.PoseSteps()).pose_start_step == 0
    rays, frames, plan, T = sphere_plan()
    result = _fit(config, rays, frames, plan, T)
    assert int(result.state.step) == 2 and np.isfinite(result.history[-1]["loss"])


def test_the_clock_stops_at_a_chunk_end(caplog):
    """The limit moves at chunk ends: a limit already spent stops after the first chunk, stopped_early says so, and the
    state is the first chunk's; 0 runs every step."""
    config = make_tiny_config(steps=6)
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    config.train.log_every, config.train.checkpoint_every = 2, 0
    rays, frames, plan, T = sphere_plan()
    with caplog.at_level("WARNING", logger="neld_jax.training.train"):
        stopped = _fit(config, rays, frames, plan, T, max_seconds=1e-9)
    assert stopped.stopped_early and int(stopped.state.step) == 2
    assert "stopping at step 2 of 6" in caplog.text
    unlimited = _fit(config, rays, frames, plan, T, max_seconds=0.0)
    assert not unlimited.stopped_early and int(unlimited.state.step) == 6


def test_steps_that_fit():
    assert train.steps_that_fit(20, 100, 100.0, 1.0, 25) == 100  # 80 steps in 100 s fit
    assert train.steps_that_fit(20, 100, 30.0, 1.0, 25) == 47  # 27 more in 30 s, 10 % in hand
    assert train.steps_that_fit(20, 100, 2.0, 1.0, 25) == 25  # never below min_total
    assert train.steps_that_fit(20, 100, 30.0, 0.0, 25) == 100  # no rate: no plan


def test_the_clock_compresses_the_plan_and_a_resumed_run_keeps_it(monkeypatch):
    """On a fake clock (1 s a step, 5 s to compile each plan's chunk) 100 planned steps cannot fit in 60 s: after the
    second chunk (35 s left, three compiles of 5 s kept in hand) the plan is compressed to the 38 that fit, and it
    runs whole (the coarse-to-fine window ends). A run resumed from that history keeps 38."""
    clock = fake_training_clock(monkeypatch)
    config = make_tiny_config(steps=100)
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    config.train.log_every, config.train.checkpoint_every = 10, 0
    rays, frames, plan, T = sphere_plan()
    result = _fit(config, rays, frames, plan, T, max_seconds=60.0)
    assert result.schedules.total_steps == 38 and int(result.state.step) == 38 and not result.stopped_early
    assert [h["total_steps"] for h in result.history[:2]] == [100, 100] and result.history[-1]["total_steps"] == 38
    assert result.history[-1]["alpha"] == config.model.pos_freqs  # the compressed window ended
    assert clock[0] <= 60.0
    resumed = _fit(config, rays, frames, plan, T, history=[{"step": 0, "total_steps": 38}])
    assert resumed.schedules.total_steps == 38 and int(resumed.state.step) == 38


def test_fit_logs_the_corrections_in_metres():
    """The history's pose_trans_mean_m is the mean translation of Exp((rho / ref_scale, omega)): V(omega) rho in
    metres, not |rho|."""
    config = make_tiny_config(steps=4)
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    config.train.fixed_scans = (0, 1, 2)  # the corrections below stay as set
    rays, frames, plan, T = sphere_plan()
    xi = np.array(
        [[0.2, -0.1, 0.3, 0.0, 0.0, 1.2], [0.0, 0.4, 0.0, 0.9, 0.0, 0.0], [0.1, 0.1, 0.1, 0.3, -0.5, 0.7]], np.float32
    )
    state = train.init_state(config, _trainer(config, plan, T), 3, 1)
    state = state.replace(params={**state.params, "poses": jnp.asarray(xi)})
    result = _fit(config, rays, frames, plan, T, state=state)
    expected = []
    for rho, omega in zip(xi[:, :3].astype(np.float64), xi[:, 3:].astype(np.float64)):
        theta = np.linalg.norm(omega)
        K = np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]])
        V = np.eye(3) + (1 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * K @ K
        expected.append(np.linalg.norm(V @ rho))
    assert abs(np.mean(np.linalg.norm(xi[:, :3], axis=1)) - np.mean(expected)) > 0.005  # |rho| would be wrong
    assert result.history[-1]["pose_trans_mean_m"] == pytest.approx(np.mean(expected), rel=1e-5)
    assert np.all(np.asarray(result.state.params["poses"]) == xi)


def test_chunks_end_at_log_steps_and_never_straddle_stages_pose_start_or_checkpoints():
    config = make_tiny_config(steps=20)  # stages start at steps 0 and 10; poses start at step 8
    schedules = train.make_schedules(config, train.PoseSteps())
    assert schedules.stage_starts == (0, 10) and schedules.pose_start_step == 8
    bounds = train.chunk_bounds(0, 20, 4, 6, schedules)  # log every 4, checkpoint every 6
    assert bounds == [(0, 4), (4, 6), (6, 8), (8, 10), (10, 12), (12, 16), (16, 18), (18, 20)]
    assert train.chunk_bounds(0, 20, 100, 0, schedules) == [(0, 8), (8, 10), (10, 20)]
    assert train.chunk_bounds(12, 20, 4, 6, schedules) == bounds[-3:]  # a resumed run cuts the same chunks
    assert train.chunk_bounds(20, 20, 4, 6, schedules) == []


def test_fit_in_chunks_equals_single_steps():
    """fit's fused loop (chunks of log_every steps, one lax.scan each) reaches the state of the step called once per
    step, bit for bit on XLA:CPU, and logs that step's metrics at the chunk ends."""
    config = make_tiny_config(steps=10)
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    config.train.pose_start_freq = 0  # poses on from step 0; no checkpoints: every chunk is 5 steps, one compile
    config.train.checkpoint_every, config.train.log_every = 0, 5
    rays, frames, plan, T = sphere_plan()
    fitted = _fit(config, rays, frames, plan, T)
    assert [h["step"] for h in fitted.history] == [5, 10]
    trainer = _trainer(config, plan, T)
    step = jax.jit(trainer.step, static_argnames=("sampler",), donate_argnums=(0,))
    state, losses = train.init_state(config, trainer, 3, 1), []
    for i in range(10):
        state, metrics = step(state, rays, frames, trainer.sampler(i))
        losses.append(float(metrics["loss"]))
    assert int(fitted.state.step) == int(state.step) == 10
    assert np.abs(np.asarray(state.params["poses"])).max() > 0  # the poses moved inside the chunks too
    _assert_trees_equal((fitted.state.params, fitted.state.opt_state), (state.params, state.opt_state))
    np.testing.assert_array_equal(jax.random.key_data(fitted.state.key), jax.random.key_data(state.key))
    assert [h["loss"] for h in fitted.history] == [losses[4], losses[9]]  # the last step of each chunk
    assert set(fitted.history[0]) >= set(metrics) | {
        "step",
        "range_err_m",
        "range_residual_median_m",
        "pose_trans_mean_m",
        "elapsed_s",
    }


def test_several_cubes_take_their_own_width_rays_termination_and_rate():
    """The (M > 1) settings: a plan of several cubes draws train.batch_rays x submaps.step_rays_factor shared among
    them, at submaps.width, submaps.lambda_termination and submaps.field_lr_from_steps; one cube keeps the run's."""
    from neld_jax.config import recording

    cpu = recording("cpu")
    assert (cpu.submaps.width, cpu.model.width, cpu.submaps.step_rays_factor) == (64, 128, 3.0)
    assert train.make_field(cpu, 1).width == 128 and train.make_field(cpu, 31).width == 64
    assert train.batch_rays_per_cube(cpu, 1) == 512 and train.batch_rays_per_cube(cpu, 31) == 49  # 1536 a step
    assert train.batch_rays_per_cube(cpu, 1000) == train.MIN_BATCH_RAYS
    assert train.loss_settings(cpu, 1).lambda_termination == 3.0 and train.loss_settings(cpu, 2).lambda_termination == 1
    own = with_budget(defaults(), "cpu").train.field_lr_init
    assert cpu.train.field_lr_init == pytest.approx(4 * own)  # recordings: 4x the budget's rate
    assert tuple(cpu.submaps.field_lr_from_steps) == (6000, 0.25)
    for steps, cubes, times in ((1500, 2, 4.0), (5999, 2, 4.0), (6000, 2, 1.0), (30_000, 2, 1.0), (30_000, 1, 4.0)):
        factor = train.field_lr_factor(cpu, cubes, steps)
        schedules = train.make_schedules(cpu, train.PoseSteps.from_config(cpu), steps, factor)
        assert float(schedules.field_lr(0)) == pytest.approx(times * own, rel=1e-6), (steps, cubes)
        assert float(schedules.field_lr(steps) / schedules.field_lr(0)) == pytest.approx(
            cpu.train.field_lr_final / cpu.train.field_lr_init, rel=1e-4
        )
    gpu = with_budget(defaults(), "gpu")
    assert train.make_field(gpu, 5).width == gpu.model.width and train.batch_rays_per_cube(gpu, 4) == 128
    for bad in ((6000,), (0, 0.25), (6000, 0.0)):
        cpu.submaps.field_lr_from_steps = bad
        with pytest.raises(ValueError, match="submaps.field_lr_from_steps"):
            train.field_lr_factor(cpu, 2, 100)


def test_a_step_over_windows_trains_every_cube_with_one_pose_row_per_keyframe():
    """Windows of 3 keyframes sharing 1: the fields stack [M, ...], the shared keyframes get one row, a step moves
    every movable row and the metrics are finite."""
    config = make_tiny_config(steps=6)
    config.train.c2f_end_fraction = 0.0
    config.train.fixed_scans = (0,)
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    config.train.log_every, config.train.checkpoint_every = 6, 0
    rays, frames, plan, T = sphere_plan(num_scans=7, per_scan=48, window=3)
    assert plan.num_submaps == 3 and frames.T_init.shape == (3, 3, 4, 4)
    result = _fit(config, rays, frames, plan, T)
    fields = jax.tree.leaves(result.state.params["fields"])
    assert all(leaf.shape[0] == 3 for leaf in fields)
    poses = np.asarray(result.state.params["poses"])
    assert poses.shape == (7, 6) and np.all(poses[0] == 0) and np.all(np.abs(poses[1:]).max(axis=1) > 0)
    assert np.isfinite(result.history[-1]["loss"]) and result.history[-1]["range_err_m"] > 0


def test_sharded_step_shared_scan_and_resume_on_8_devices(tmp_path):
    # The suite's own XLA flags kept (conftest: unoptimised, 88 -> 43 s here), eight host devices added.
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=8".strip()
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, os.path.join(HERE, "devices_check.py"), str(tmp_path)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for check in ("sharded step equals unsharded", "shared scan gradient", "resume with sharded state"):
        assert f"OK {check}" in proc.stdout, proc.stdout


def test_bfloat16_matmuls_render_depth_close_to_float32_and_give_gradients():
    """model.matmul_dtype=bfloat16 on the trained sphere field (float32 parameters): rendered depths within ~1% of
    float32's, and finite parameter gradients through the bfloat16 matmuls (the training path)."""
    from neld_jax.field.model import render_rays, world_rays

    config, rays, frames, plan, T, result = _sphere_fit()
    params = jax.tree.map(lambda x: x[0], result.state.params["fields"])
    field32 = train.make_field(config)
    field16 = field32.clone(matmul_dtype="bfloat16")
    assert field32.matmul_dtype == "float32"
    sampler = train.sampler_settings(config.sampling, 16, 8)
    n = int(rays.num_rays[0])
    Tn = jnp.asarray(T, jnp.float32)[rays.scan_index[0, :n]]
    origins, directions = world_rays(Tn, rays.directions[0, :n])
    ranges = rays.ranges[0, :n]

    def depth_loss(field_params, field):
        depth = render_rays(field_params, field, sampler, origins, directions, jnp.asarray(8.0)).fine.depth
        return jnp.mean(jnp.abs(depth - ranges)), depth

    depth32 = np.asarray(jax.jit(lambda p: depth_loss(p, field32)[1])(params))
    (_, depth16), grads = jax.jit(jax.value_and_grad(lambda p: depth_loss(p, field16), has_aux=True))(params)
    difference = np.abs(np.asarray(depth16) - depth32)
    ranges = np.asarray(ranges)
    assert np.median(difference) < 0.01 * np.median(ranges), np.median(difference)
    assert difference.max() > 0  # the two really ran different matmuls
    assert np.median(np.abs(np.asarray(depth16) - ranges)) < 1.5 * np.median(np.abs(depth32 - ranges)) + 1e-3
    leaves = jax.tree.leaves(grads)
    assert all(g.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(g))) for g in leaves)
    assert max(float(jnp.abs(g).max()) for g in leaves) > 0
    assert "xbf16>" in jax.jit(lambda p: depth_loss(p, field16)[1]).lower(params).as_text()  # bfloat16 operands

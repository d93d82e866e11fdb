"""The rendered map (steps.mapping): every ray by default, a uniform sample of them under a time limit, one cube
or several stitched, points in the world."""

import dataclasses

import numpy as np
from conftest import make_tiny_config, sphere_plan

from neld_jax.steps import mapping
from neld_jax.steps.mapping import render_map, render_order
from neld_jax.steps.refine import Refined
from neld_jax.training import train
from neld_jax.training.rays import sphere_scene_rays


def _refined(window: int = 0, num_scans: int = 4):
    """An untrained field over the sphere scene (metres = cube units), as refine would hand it to the map."""
    config = make_tiny_config()
    _, _, plan, T = sphere_plan(num_scans=num_scans, window=window)
    trainer = train.make_trainer(config, num_scans, plan.num_submaps, train.PoseSteps(), T)
    state = train.init_state(config, trainer, num_scans, plan.num_submaps)
    result = train.FitResult(state, [], False, 0.0, trainer.schedules)
    return config, Refined(result, plan, trainer.field, T, T, np.eye(4), np.zeros(num_scans, np.int64))


def _render(max_seconds: float, monkeypatch, window: int = 0):
    monkeypatch.setattr(mapping, "RAYS_PER_BATCH", 64)
    config, refined = _refined(window)
    rays, _ = sphere_scene_rays(num_scans=4, rays_per_scan=100, seed=0)
    sampler = dataclasses.replace(train.sampler_settings(config.sampling, 8, 8), guided_samples=0)
    render = render_map(refined, rays, sampler, min_opacity=0.0, max_seconds=max_seconds, seed=3)
    return render, np.asarray(rays.scan_index)


def test_without_a_limit_every_ray_is_rendered(monkeypatch):
    render, _ = _render(0.0, monkeypatch)
    assert render.num_rendered == 400 and np.isfinite(render.ranges).all()
    assert render.points.shape == (400, 3)  # min_opacity 0: every ray gives a point
    assert np.all(render.ranges > 0)


def test_a_time_limit_renders_a_uniform_sample_and_marks_the_rest(monkeypatch):
    full, scan_index = _render(0.0, monkeypatch)
    # A limit that has passed after the first batch: that batch's 64 rays are rendered, the others are NaN.
    limited, _ = _render(1e-9, monkeypatch)
    rendered = np.isfinite(limited.opacity)
    assert limited.num_rendered == 64 and rendered.sum() == 64 and limited.points.shape == (64, 3)
    assert np.array_equal(np.isfinite(limited.ranges), rendered)
    # The rays of the first batch are those of the seeded random order, from every scan, not the first scan's.
    np.testing.assert_array_equal(np.flatnonzero(rendered), np.sort(render_order(400, 1e-9, seed=3)[:64]))
    assert set(scan_index[rendered]) == {0, 1, 2, 3}
    # The same rays render to the same ranges whatever order they went in.
    np.testing.assert_allclose(limited.ranges[rendered], full.ranges[rendered], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(limited.opacity[rendered], full.opacity[rendered], rtol=1e-5, atol=1e-6)


def test_no_batch_is_started_that_would_end_past_the_limit(monkeypatch):
    """On a clock that moves 1 s at every reading (the render reads it at its start and at each part's start and
    end), each batch takes 1 s and the third ends at 6 s. With a 6.5 s limit a fourth, as long, would end past it,
    so three batches run (a rule that only stopped once the limit had passed would start the fourth)."""
    import types

    ticks = iter(range(10_000))
    monkeypatch.setattr(mapping, "time", types.SimpleNamespace(perf_counter=lambda: float(next(ticks))))
    limited, _ = _render(6.5, monkeypatch)
    assert limited.num_rendered == 3 * 64


def test_several_cubes_render_every_ray_once_from_the_most_central_cube(monkeypatch):
    # Windows of 2 keyframes sharing 1: 3 cubes; a ray of a shared keyframe is rendered by both of its cubes and
    # kept from one; under a limit every cube renders the same quarter of the rays.
    full, _ = _render(0.0, monkeypatch, window=2)
    assert full.num_rendered == 400 and full.points.shape == (400, 3)
    limited, _ = _render(1e-9, monkeypatch, window=2)
    assert limited.num_rendered == len(np.array_split(np.arange(400), mapping.RENDER_PARTS)[0])


def test_render_order_is_the_rays_own_order_without_a_limit():
    np.testing.assert_array_equal(render_order(10, 0.0, seed=1), np.arange(10))
    order = render_order(10, 5.0, seed=1)
    assert sorted(order) == list(range(10)) and not np.array_equal(order, np.arange(10))

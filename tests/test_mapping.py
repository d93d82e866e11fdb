"""The rendered map's renderer: every ray by default, a uniform sample of them under a time limit."""

import dataclasses

import numpy as np

from conftest import make_tiny_config
from neld_jax import train
from neld_jax.data.rays import sphere_scene_rays
from neld_jax.mapping import render_map, render_order


def _render(max_seconds: float, rays_per_batch: int = 64):
    config = make_tiny_config()
    rays, T_init = sphere_scene_rays(num_scans=4, rays_per_scan=100, seed=0)
    setup = train.create_train_state(config, 4, 1.0)
    sampler = dataclasses.replace(train.sampler_settings(config, 1.0, 8, 8), guided_samples=0)
    render = render_map(setup.state.params["field"], setup.field, sampler, T_init, np.asarray(rays.directions),
                        np.asarray(rays.scan_index), float(config.model.pos_freqs), rays_per_batch=rays_per_batch,
                        min_opacity=0.0, max_seconds=max_seconds, seed=3)
    return render, np.asarray(rays.scan_index)


def test_without_a_limit_every_ray_is_rendered():
    render, _ = _render(max_seconds=0.0)
    assert render.num_rendered == 400 and np.isfinite(render.ranges).all()
    assert render.points.shape == (400, 3)  # min_opacity 0: every ray gives a point


def test_a_time_limit_renders_a_uniform_sample_and_marks_the_rest():
    full, scan_index = _render(max_seconds=0.0)
    # A limit that has passed after the first batch: that batch's 64 rays are rendered, the others are NaN.
    limited, _ = _render(max_seconds=1e-9)
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
    """On a clock that moves 1 s at every reading (the render reads it at its start and at each batch's start and
    end), each batch takes 1 s and the third ends at 6 s. With a 6.5 s limit a fourth, as long, would end past it,
    so three batches run (a rule that only stopped once the limit had passed would start the fourth)."""
    import types

    from neld_jax import mapping

    ticks = iter(range(10_000))
    monkeypatch.setattr(mapping, "time", types.SimpleNamespace(perf_counter=lambda: float(next(ticks))))
    limited, _ = _render(max_seconds=6.5)
    assert limited.num_rendered == 3 * 64


def test_render_order_is_the_rays_own_order_without_a_limit():
    np.testing.assert_array_equal(render_order(10, 0.0, seed=1), np.arange(10))
    order = render_order(10, 5.0, seed=1)
    assert sorted(order) == list(range(10)) and not np.array_equal(order, np.arange(10))

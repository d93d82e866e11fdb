"""Alpha compositing (eqs. 2-3): robustness for extreme densities, step densities, map range (eq. 14)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neld_jax.field import rendering

composite = jax.jit(rendering.composite)
depth_gradient = jax.jit(jax.grad(lambda sigma, z, z_far: jnp.sum(rendering.composite(sigma, z, z_far).depth)))


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


def _samples(num_rays=4, num_samples=64, near=0.1, far=2.1):
    z = jnp.broadcast_to(jnp.linspace(near, far, num_samples, endpoint=False), (num_rays, num_samples))
    return z + 0.0, jnp.full((num_rays,), far)


def test_deltas_from_samples():
    z = jnp.array([[0.0, 0.5, 1.5], [1.0, 2.0, 2.5]])
    np.testing.assert_allclose(rendering.deltas_from_samples(z), [[0.5, 1.0, 1.0], [1.0, 0.5, 0.5]])
    with_far = rendering.deltas_from_samples(z, jnp.array([2.0, 2.0]))
    np.testing.assert_allclose(with_far, [[0.5, 1.0, 0.5], [1.0, 0.5, 0.0]])  # clipped at 0


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_values_and_gradients_finite_for_extreme_densities(dtype):
    z, z_far = _samples()
    z, z_far = z.astype(dtype), z_far.astype(dtype)
    magnitudes = 10.0 ** np.arange(-10, 11, 2)  # 1e-10 ... 1e10
    rng = np.random.default_rng(0)
    for scale in magnitudes:
        sigma = jnp.asarray(scale * rng.uniform(0.0, 1.0, size=z.shape), dtype=dtype).at[:, 0].set(0.0)
        out = composite(sigma, z, z_far)
        for value in out:
            assert np.all(np.isfinite(value)), scale
        assert np.all(np.asarray(out.opacity) <= 1.0 + 1e-6) and np.all(np.asarray(out.weights) >= 0.0)
        grad = depth_gradient(sigma, z, z_far)
        assert np.all(np.isfinite(grad)), scale
    # Opaque from the first sample: all weight there, nothing behind it.
    out = composite(jnp.full(z.shape, 1e10, dtype=dtype), z, z_far)
    np.testing.assert_allclose(out.weights[:, 0], 1.0, rtol=1e-6)
    np.testing.assert_allclose(out.depth, z[:, 0], rtol=1e-6)


def test_weights_match_the_textbook_formula():
    rng = np.random.default_rng(1)
    z = np.sort(rng.uniform(0.1, 2.0, size=(3, 12)), axis=-1)
    z_far = np.full(3, 2.2)
    sigma = rng.uniform(0.0, 5.0, size=(3, 12))
    deltas = np.concatenate([np.diff(z, axis=-1), z_far[:, None] - z[:, -1:]], axis=-1)
    transmittance = np.exp(-np.concatenate([np.zeros((3, 1)), np.cumsum(sigma * deltas, -1)[:, :-1]], -1))
    expected = transmittance * (1.0 - np.exp(-sigma * deltas))
    out = composite(jnp.asarray(sigma), jnp.asarray(z), jnp.asarray(z_far))
    np.testing.assert_allclose(out.weights, expected, rtol=1e-12)
    np.testing.assert_allclose(out.depth, np.sum(expected * z, -1), rtol=1e-12)  # not divided by opacity
    np.testing.assert_allclose(out.opacity, expected.sum(-1), rtol=1e-12)
    np.testing.assert_allclose(out.deltas, deltas)


@pytest.mark.parametrize("step", [0.537, 1.003, 1.71])
def test_expected_range_of_a_step_density_is_the_step(step):
    z, z_far = _samples(num_rays=1, num_samples=200)  # spacing 0.01
    spacing = float(z[0, 1] - z[0, 0])
    sigma = jnp.where(z > step, 1e6, 0.0)
    out = composite(sigma, z, z_far)
    assert abs(float(out.depth[0]) - step) <= spacing
    np.testing.assert_allclose(out.opacity, 1.0, atol=1e-9)
    assert abs(float(rendering.map_range(out.weights, out.deltas, z)[0]) - step) <= spacing


def test_map_range_uses_density_not_weight_and_guards_zero_spacing():
    # Same weight, different spacing: the narrower bin has the higher termination density.
    weights = jnp.array([[0.3, 0.3, 0.0, 0.0]])
    deltas = jnp.array([[0.2, 0.05, 0.1, 0.0]])
    z = jnp.array([[1.0, 1.2, 1.25, 1.35]])
    np.testing.assert_allclose(rendering.map_range(weights, deltas, z), [1.2])
    # A zero spacing (last sample at z_far) never wins and never divides by zero.
    out = rendering.map_range(jnp.array([[0.1, 0.0]]), jnp.array([[0.1, 0.0]]), jnp.array([[0.5, 0.6]]))
    np.testing.assert_allclose(out, [0.5])


def test_rendered_map_rays_per_scan_caps_the_sequence_total():
    from neld_jax.training.rays import rays_per_scan

    assert rays_per_scan(0, 0, 10) is None  # every ray
    assert rays_per_scan(2048, 0, 266) == 2048  # only the per-scan limit
    assert rays_per_scan(2048, 262_144, 24) == 2048  # a short sequence stays under the total
    assert rays_per_scan(2048, 262_144, 266) == 262_144 // 266  # a long one shares the total
    assert rays_per_scan(0, 262_144, 266) == 262_144 // 266
    assert rays_per_scan(2048, 262_144, 5000) == 256  # the floor a scan keeps for its residuals
    assert rays_per_scan(64, 262_144, 5000) == 64  # the floor never overrides a smaller per-scan limit

"""Range L1 and termination losses on hand-built rays."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neld_jax.field import losses


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


def test_range_l1_with_and_without_mask():
    pred = jnp.array([1.0, 2.5, 3.0, jnp.nan])
    target = jnp.array([1.5, 2.0, 1.0, 0.0])
    mask = jnp.array([True, True, True, False])
    np.testing.assert_allclose(losses.range_l1(pred, target, mask), (0.5 + 0.5 + 2.0) / 3)
    np.testing.assert_allclose(losses.range_l1(pred[:3], target[:3]), (0.5 + 0.5 + 2.0) / 3)
    np.testing.assert_allclose(losses.range_l1(pred, target, jnp.array([1.0, 0.0, 0.0, 0.0])), 0.5)
    assert float(losses.range_l1(pred, target, jnp.zeros(4, bool))) == 0.0  # all masked: 0, not NaN
    grad = jax.grad(lambda p: losses.range_l1(p, target, mask))(pred)
    np.testing.assert_allclose(grad, [-1 / 3, 1 / 3, 1 / 3, 0.0])  # masked NaN ray sends no NaN back


def test_termination_index():
    z = jnp.array([[0.5, 1.0, 1.5, 2.0], [0.5, 1.0, 1.5, 2.0], [0.5, 1.0, 1.5, 2.0]])
    idx, valid = losses.termination_index(z, jnp.array([1.2, 1.0, 2.5]))
    np.testing.assert_array_equal(idx[:2], [2, 2])  # first sample strictly beyond the range
    np.testing.assert_array_equal(valid, [True, True, False])


def test_termination_loss_hand_built():
    z = jnp.array([[0.5, 1.0, 1.5, 2.0], [0.5, 1.0, 1.5, 2.0], [0.5, 1.0, 1.5, 2.0]])
    weights = jnp.array([[0.1, 0.2, 0.6, 0.1], [0.0, 0.0, 0.0, 0.0], [0.3, 0.3, 0.3, 0.1]])
    target = jnp.array([1.2, 1.2, 3.0])  # the third ray has no sample beyond its range: not counted
    eps = 1e-10
    expected = (-np.log(0.6) - np.log(eps)) / 2  # second ray: h = 0 is clamped to eps, not ln 0
    np.testing.assert_allclose(losses.termination_loss(weights, z, target, eps=eps), expected)
    mask = jnp.array([True, False, True])
    np.testing.assert_allclose(losses.termination_loss(weights, z, target, mask), -np.log(0.6))
    # A perfect termination distribution costs nothing.
    perfect = jnp.array([[0.0, 0.0, 1.0, 0.0]])
    np.testing.assert_allclose(losses.termination_loss(perfect, z[:1], target[:1]), 0.0, atol=1e-15)
    # Gradients are finite at h = 0 and push h[n*] up where it is positive.
    grad = jax.grad(lambda w: losses.termination_loss(w, z, target))(weights)
    assert np.all(np.isfinite(grad))
    assert grad[0, 2] < 0 and np.all(grad[0, [0, 1, 3]] == 0)
    np.testing.assert_array_equal(grad[2], 0.0)


def test_losses_jit():
    z = jnp.tile(jnp.linspace(0.1, 2.0, 8), (5, 1))
    weights = jnp.full((5, 8), 0.1)
    target = jnp.linspace(0.5, 1.5, 5)
    value = jax.jit(losses.termination_loss)(weights, z, target, jnp.ones(5, bool))
    np.testing.assert_allclose(value, -np.log(0.1))
    assert np.isfinite(float(jax.jit(losses.range_l1)(target, target * 2)))

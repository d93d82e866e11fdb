"""Fourier encoding: forward values, the surrogate gradient of eq. 9, and BARF's window."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import encoded_dim
from jax.test_util import check_grads

from neld_jax.field.encoding import barf_window, fourier_encode

NUM_FREQS = 5


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


def _plain_encoding(x, num_freqs, window=None):
    """gamma(x) written out directly: [x, cos(2^k pi x) k-major, sin(2^k pi x) k-major]."""
    scales = 2.0 ** np.arange(num_freqs) * np.pi
    w = np.ones(num_freqs) if window is None else window
    cos = [w[k] * jnp.cos(scales[k] * x) for k in range(num_freqs)]
    sin = [w[k] * jnp.sin(scales[k] * x) for k in range(num_freqs)]
    return jnp.concatenate([x] + cos + sin, axis=-1)


def _surrogate_primal(x, num_freqs, window=None):
    """The function whose ordinary gradient the surrogate claims: gamma_k / (2^k pi), identity kept."""
    scales = 2.0 ** np.arange(num_freqs) * np.pi
    w = np.ones(num_freqs) if window is None else window
    cos = [w[k] * jnp.cos(scales[k] * x) / scales[k] for k in range(num_freqs)]
    sin = [w[k] * jnp.sin(scales[k] * x) / scales[k] for k in range(num_freqs)]
    return jnp.concatenate([x] + cos + sin, axis=-1)


def _points(seed=0, shape=(4, 3)):
    return jnp.asarray(np.random.default_rng(seed).uniform(-1, 1, size=shape))


def test_forward_equals_plain_encoding_and_layout():
    x = _points()
    for surrogate in (True, False):
        out = fourier_encode(x, NUM_FREQS, surrogate=surrogate)
        assert out.shape == (4, encoded_dim(3, NUM_FREQS)) == (4, 3 * (1 + 2 * NUM_FREQS))
        np.testing.assert_allclose(out, _plain_encoding(x, NUM_FREQS), atol=1e-14)
    # Layout spot checks: identity first, then cos of frequency 1 for input 2 at 3 + 1*3 + 2.
    out = np.asarray(fourier_encode(x, NUM_FREQS))
    np.testing.assert_allclose(out[:, :3], x)
    np.testing.assert_allclose(out[:, 3 + 3 + 2], np.cos(2 * np.pi * x[:, 2]), atol=1e-14)
    np.testing.assert_allclose(out[:, 3 + 3 * NUM_FREQS + 3 + 2], np.sin(2 * np.pi * x[:, 2]), atol=1e-14)
    assert fourier_encode(x, 0).shape == (4, 3)


def test_batched_leading_axes():
    x = _points(1, (2, 5, 3))
    assert fourier_encode(x, NUM_FREQS).shape == (2, 5, encoded_dim(3, NUM_FREQS))


def test_surrogate_gradient_divides_each_frequency_by_its_amplification():
    x = _points(2, (3,))  # one point, jacobian [out, 3]
    exact = np.asarray(jax.jacrev(lambda v: fourier_encode(v, NUM_FREQS, surrogate=False))(x))
    surrogate = np.asarray(jax.jacrev(lambda v: fourier_encode(v, NUM_FREQS, surrogate=True))(x))
    np.testing.assert_allclose(exact, jax.jacfwd(lambda v: _plain_encoding(v, NUM_FREQS))(x), atol=1e-12)
    per_frequency = np.repeat(2.0 ** np.arange(NUM_FREQS) * np.pi, 3)  # k-major, 3 inputs each
    divisor = np.concatenate([np.ones(3), per_frequency, per_frequency])  # rows [x | cos | sin]
    np.testing.assert_allclose(surrogate, exact / divisor[:, None], atol=1e-12)
    # The identity rows keep their ordinary gradient; the highest frequency is really damped.
    np.testing.assert_allclose(surrogate[:3], np.eye(3))
    assert np.abs(exact[-1]).max() > 40 * np.abs(surrogate[-1]).max()


def _routes_gradient_through_encoding(primal_reference, encoded):
    """Values of primal_reference, gradient of `encoded` (the custom vjp under test)."""

    def f(x):
        return jax.lax.stop_gradient(primal_reference(x) - encoded(x)) + encoded(x)

    return f


def test_check_grads_surrogate_is_gradient_of_scaled_encoding():
    # check_grads compares the reverse-mode derivative with finite differences of the forward values; the
    # combined function has the values of gamma_k / (2^k pi) and the vjp of the surrogate encoding, so it
    # passes only if the custom vjp is exactly the derivative the paper's eq. 9 describes.
    x = _points(3, (2, 3))
    window = np.array([1.0, 1.0, 0.7, 0.2, 0.0])
    for w in (None, window):
        f = _routes_gradient_through_encoding(
            lambda v, w=w: _surrogate_primal(v, NUM_FREQS, w),
            lambda v, w=w: fourier_encode(v, NUM_FREQS, None if w is None else jnp.asarray(w), surrogate=True),
        )
        check_grads(f, (x,), order=1, modes=("rev",), atol=1e-7, rtol=1e-7, eps=1e-6)
    # And the exact mode's gradient is the ordinary one.
    exact = lambda v: fourier_encode(v, NUM_FREQS, surrogate=False)  # noqa: E731
    check_grads(exact, (x,), order=1, modes=("rev", "fwd"), eps=1e-6)


def test_window_multiplies_features_and_gets_no_gradient():
    x = _points(4)
    window = jnp.array([1.0, 0.5, 0.25, 0.0, 0.0])
    out = fourier_encode(x, NUM_FREQS, window)
    np.testing.assert_allclose(out, _plain_encoding(x, NUM_FREQS, np.asarray(window)), atol=1e-14)
    grad_window = jax.grad(lambda w: jnp.sum(fourier_encode(x, NUM_FREQS, w) ** 2))(window)
    np.testing.assert_array_equal(grad_window, 0.0)
    # A switched-off frequency passes no gradient to x either.
    jac = jax.jacrev(lambda v: fourier_encode(v, NUM_FREQS, window))(x[0])
    np.testing.assert_array_equal(jac[3 + 3 * 3 : 3 + 3 * 5], 0.0)


def test_barf_window():
    L = 6
    np.testing.assert_array_equal(barf_window(0.0, L), np.zeros(L))
    np.testing.assert_allclose(barf_window(float(L), L), np.ones(L))
    np.testing.assert_allclose(barf_window(2.5, L), [1.0, 1.0, 0.5, 0.0, 0.0, 0.0], atol=1e-7)
    alphas = np.linspace(0.0, L, 61)
    windows = np.stack([np.asarray(barf_window(a, L)) for a in alphas])
    assert np.all(np.diff(windows, axis=0) >= -1e-7), "each weight grows with alpha"
    assert np.all(np.diff(windows, axis=1) <= 1e-7), "lower frequencies switch on first"
    assert np.all((windows >= 0) & (windows <= 1))
    # alpha may be traced.
    traced = jax.jit(lambda a: barf_window(a, L))(jnp.asarray(3.25))
    np.testing.assert_allclose(traced, barf_window(3.25, L))


def test_sin_pi_matches_numpy_in_float64():
    """The polynomial sin(pi t) of the encoding, and cos(pi t) = sin(pi (t + 1/2)), against numpy over a wide
    range incl. half-integers and negatives; its derivative is pi cos(pi t), also in forward mode."""
    from neld_jax.field.encoding import sin_pi

    with jax.enable_x64(True):
        t = np.concatenate([np.linspace(-600.0, 600.0, 200_001), np.arange(-40, 41) / 2.0, [-0.25, 0.25, 1e-9]])
        tj = jnp.asarray(t, jnp.float64)
        np.testing.assert_allclose(np.asarray(sin_pi(tj)), np.sin(np.pi * t), atol=1e-12)
        np.testing.assert_allclose(np.asarray(sin_pi(tj + 0.5)), np.cos(np.pi * t), atol=1e-12)
        derivative = jax.vmap(jax.grad(sin_pi))(tj)
        np.testing.assert_allclose(np.asarray(derivative), np.pi * np.cos(np.pi * t), atol=1e-11)
        _, tangent = jax.jvp(sin_pi, (tj,), (jnp.ones_like(tj),))
        np.testing.assert_allclose(np.asarray(tangent), np.pi * np.cos(np.pi * t), atol=1e-11)
    # float32: within a few ulp of the exact value at the float32 input (jnp.sin(pi * t) is off by up to ~1e-4).
    t32 = np.random.default_rng(0).uniform(-512.0, 512.0, 100_000).astype(np.float32)
    exact = np.sin(np.pi * t32.astype(np.float64))
    assert np.abs(np.asarray(sin_pi(jnp.asarray(t32))) - exact).max() < 5e-7

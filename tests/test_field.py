"""The density MLP: shapes, non-negativity, jit, finite gradients, parameter count."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neld_jax.encoding import barf_window, encoded_dim
from neld_jax.field import DensityField


def _inputs(n=64, seed=0):
    rng = np.random.default_rng(seed)
    positions = jnp.asarray(rng.uniform(-1, 1, size=(n, 3)), jnp.float32)
    view_dirs = jnp.asarray(np.stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-0.5, 0.5, n)], -1), jnp.float32)
    return positions, view_dirs


def _param_count(params):
    return sum(int(np.prod(p.shape)) for p in jax.tree.leaves(params))


def test_paper_sized_parameter_count():
    # Shapes only (no arrays): width 512, 8 layers, skip at 4, L = 15 / 4, view-dependent head.
    field = DensityField()
    shapes = jax.eval_shape(field.init, jax.random.key(0), jnp.zeros((1, 3)), jnp.zeros((1, 2)))
    pos, dirs, w = encoded_dim(3, 15), encoded_dim(2, 4), 512
    expected = (pos * w + w) + 6 * (w * w + w) + ((w + pos) * w + w) + ((w + dirs) * (w // 2) + w // 2) + (w // 2 + 1)
    assert _param_count(shapes) == expected


@pytest.mark.parametrize("activation", ["softplus", "relu"])
@pytest.mark.parametrize("use_view_dirs", [True, False])
def test_output_shape_non_negative_and_small_at_init(activation, use_view_dirs):
    field = DensityField(
        width=32, depth=3, skip_layers=(2,), pos_freqs=6, dir_freqs=2,
        density_activation=activation, use_view_dirs=use_view_dirs,
    )
    positions, view_dirs = _inputs()
    params = jax.jit(field.init)(jax.random.key(1), positions, view_dirs)
    sigma = jax.jit(field.apply)(params, positions, view_dirs)
    assert sigma.shape == (64,) and sigma.dtype == jnp.float32
    assert np.all(np.asarray(sigma) >= 0)
    # Untrained: close to the small positive initial density everywhere (no dead, no opaque start).
    assert np.all(np.abs(np.asarray(sigma) - field.initial_density) < 0.05)
    # Leading axes are kept.
    sigma_grid = jax.jit(field.apply)(params, positions.reshape(4, 16, 3), view_dirs.reshape(4, 16, 2))
    np.testing.assert_allclose(sigma_grid.reshape(-1), sigma, rtol=1e-5, atol=1e-6)
    if not use_view_dirs:
        assert "density_hidden" not in params["params"]


def test_gradients_finite_and_window_switches_frequencies_off():
    field = DensityField(width=32, depth=4, skip_layers=(2,), pos_freqs=8, dir_freqs=2)
    positions, view_dirs = _inputs(32, seed=2)
    params = jax.jit(field.init)(jax.random.key(3), positions, view_dirs)
    # Make the field non-trivial (the output layer starts tiny) so the gradient wrt positions is not ~0.
    params = jax.tree.map(lambda p: p * 3.0, params)
    params["params"]["density_out"]["kernel"] = params["params"]["density_out"]["kernel"] * 100.0

    @jax.jit
    def position_gradient(params, positions, window):
        return jax.grad(lambda x: jnp.sum(field.apply(params, x, view_dirs, window)))(positions)

    full = np.asarray(position_gradient(params, positions, barf_window(8.0, 8)))
    assert np.all(np.isfinite(full)) and np.abs(full).max() > 0
    # With every frequency off only the identity feature carries position: the output is smooth in x,
    # so the gradient field varies much less from point to point than with all frequencies on.
    coarse = np.asarray(position_gradient(params, positions, barf_window(0.0, 8)))
    assert np.all(np.isfinite(coarse))
    assert np.std(coarse, axis=0).sum() < np.std(full, axis=0).sum()
    grads = jax.jit(jax.grad(lambda p: jnp.sum(field.apply(p, positions, view_dirs))))(params)
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))


def test_surrogate_flag_changes_only_the_backward_pass():
    kwargs = dict(width=16, depth=2, skip_layers=(1,), pos_freqs=6, dir_freqs=2)
    positions, view_dirs = _inputs(8, seed=4)
    smooth, exact = DensityField(surrogate=True, **kwargs), DensityField(surrogate=False, **kwargs)
    params = jax.jit(smooth.init)(jax.random.key(5), positions, view_dirs)
    np.testing.assert_allclose(
        jax.jit(smooth.apply)(params, positions, view_dirs), jax.jit(exact.apply)(params, positions, view_dirs)
    )

    def grad_norm(module):
        g = jax.jit(jax.grad(lambda x: jnp.sum(module.apply(params, x, view_dirs))))(positions)
        return float(jnp.linalg.norm(g))

    assert grad_norm(exact) > grad_norm(smooth)  # the exact gradient carries the 2^k pi amplification


def test_unknown_activation_is_rejected():
    with pytest.raises(ValueError, match="density_activation"):
        DensityField(width=8, depth=1, density_activation="tanh").init(jax.random.key(0), *_inputs(2))

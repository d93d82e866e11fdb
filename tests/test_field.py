"""The density MLP: shapes, non-negativity, jit, finite gradients, parameter count."""

from functools import lru_cache

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import encoded_dim

from neld_jax.field.density import DensityField
from neld_jax.field.encoding import barf_window

SMALL = dict(width=32, depth=3, skip_layers=(2,), pos_freqs=6, dir_freqs=2)


def _inputs(n=64, seed=0):
    rng = np.random.default_rng(seed)
    positions = jnp.asarray(rng.uniform(-1, 1, size=(n, 3)), jnp.float32)
    view_dirs = rng.normal(size=(n, 3))
    view_dirs = jnp.asarray(view_dirs / np.linalg.norm(view_dirs, axis=1, keepdims=True), jnp.float32)
    return positions, view_dirs


@lru_cache(maxsize=None)
def _initial_params():
    """One real initialisation, shared by the tests (XLA-compiling the initialisers is the slow part; the surrogate
    flag does not change the parameters)."""
    return jax.jit(DensityField(**SMALL).init)(jax.random.key(1), *_inputs(4))


def _param_count(params):
    return sum(int(np.prod(p.shape)) for p in jax.tree.leaves(params))


def test_paper_sized_parameter_count():
    # Shapes only (no arrays): width 512, 8 layers, skip at 4, L = 15 / 4, view-dependent head.
    field = DensityField()
    shapes = jax.eval_shape(field.init, jax.random.key(0), jnp.zeros((1, 3)), jnp.zeros((1, 3)))
    pos, dirs, w = encoded_dim(3, 15), encoded_dim(3, 4), 512
    first, hidden, skip = pos * w + w, w * w + w, (w + pos) * w + w
    head = (w + dirs) * (w // 2) + w // 2 + (w // 2 + 1)
    assert _param_count(shapes) == first + 6 * hidden + skip + head


def test_output_shape_non_negative_and_small_at_init():
    field = DensityField(**SMALL)
    positions, view_dirs = _inputs()
    params = _initial_params()
    sigma = jax.jit(field.apply)(params, positions, view_dirs)
    assert sigma.shape == (64,) and sigma.dtype == jnp.float32
    assert np.all(np.asarray(sigma) >= 0)
    # Untrained: close to the small positive initial density everywhere (no dead, no opaque start).
    assert np.all(np.abs(np.asarray(sigma) - field.initial_density) < 0.05)


def test_leading_axes_are_kept():
    field = DensityField(**SMALL)
    positions, view_dirs = _inputs()
    params = _initial_params()
    apply = jax.jit(field.apply)
    flat = apply(params, positions, view_dirs)
    grid = apply(params, positions.reshape(4, 16, 3), view_dirs.reshape(4, 16, 3))
    assert grid.shape == (4, 16)
    np.testing.assert_allclose(grid.reshape(-1), flat, rtol=1e-5, atol=1e-6)


def _trained_looking_params():
    """Initial parameters scaled up (the output layer starts tiny) so the field varies with position."""
    params = jax.tree.map(lambda p: p * 3.0, _initial_params())
    params["params"]["density_out"]["kernel"] = params["params"]["density_out"]["kernel"] * 100.0
    return params


def test_gradients_finite_and_window_switches_frequencies_off():
    field = DensityField(**SMALL)
    params = _trained_looking_params()
    positions, view_dirs = _inputs(32, seed=2)

    @jax.jit
    def gradients(params, window):
        def total(p, x):
            return jnp.sum(field.apply(p, x, view_dirs, window))

        return jax.grad(total, argnums=(0, 1))(params, positions)

    param_grads, full = gradients(params, barf_window(6.0, 6))
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(param_grads))
    assert np.all(np.isfinite(full)) and np.abs(full).max() > 0
    # With every frequency off only the identity feature carries position: the output is smooth in x,
    # so the gradient varies much less from point to point than with all frequencies on.
    _, coarse = gradients(params, barf_window(0.0, 6))
    assert np.all(np.isfinite(coarse))
    assert np.std(np.asarray(coarse), axis=0).sum() < np.std(np.asarray(full), axis=0).sum()


def test_surrogate_flag_changes_only_the_backward_pass():
    smooth, exact = DensityField(surrogate=True, **SMALL), DensityField(surrogate=False, **SMALL)
    params = _trained_looking_params()
    positions, view_dirs = _inputs(8, seed=4)
    np.testing.assert_allclose(
        jax.jit(smooth.apply)(params, positions, view_dirs), jax.jit(exact.apply)(params, positions, view_dirs)
    )

    def grad_norm(module):
        g = jax.jit(jax.grad(lambda x: jnp.sum(module.apply(params, x, view_dirs))))(positions)
        return float(jnp.linalg.norm(g))

    assert grad_norm(exact) > 2 * grad_norm(smooth)  # the exact gradient carries the 2^k pi amplification


def test_unknown_matmul_dtype_is_rejected():
    with pytest.raises(ValueError, match="matmul_dtype"):
        DensityField(width=8, depth=1, matmul_dtype="float16").init(jax.random.key(0), *_inputs(2))


def test_field_from_config_sets_every_architecture_field():
    """Each DensityField setting has a config.model field that reaches the module (surrogate: surrogate_gradient)."""
    import dataclasses

    from neld_jax.config import defaults
    from neld_jax.field.density import field_from_config

    model = defaults().model
    names = {"surrogate": "surrogate_gradient"}
    # initial_density is a constant of the architecture, not a setting
    options = [
        f.name for f in dataclasses.fields(DensityField) if f.name not in ("dtype", "parent", "name", "initial_density")
    ]
    assert set(options) >= {"width", "depth", "skip_layers", "matmul_dtype"}
    # Every option's default is the config's default ...
    default = field_from_config(model)
    assert default == DensityField(), [o for o in options if getattr(default, o) != getattr(DensityField(), o)]
    # ... and a changed config value changes the module.
    changed = dict(
        width=8, depth=2, skip_layers=[1], pos_freqs=3, dir_freqs=1, surrogate_gradient=False, matmul_dtype="bfloat16"
    )
    assert {names.get(o, o) for o in options} == set(changed)
    model.update(changed)
    field = field_from_config(model)
    for option in options:
        expected = changed[names.get(option, option)]
        assert getattr(field, option) == (tuple(expected) if option == "skip_layers" else expected), option
    hash(field)  # a static jit argument

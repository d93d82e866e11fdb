"""Every public function of the core modules compiles under jax.jit, in float32 (the training dtype),
with traced arrays wherever the trainer passes them (keys, windows, alpha), and gives finite values."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neld_jax import encoding, lie, losses, rendering, sampling
from neld_jax.field import DensityField

R, N, NF = 4, 8, 6
KEY = jax.random.key(0)
_rng = np.random.default_rng(0)
XI = jnp.asarray(_rng.normal(size=(R, 6)) * 0.3, jnp.float32)
T = lie.se3_exp(XI)
POINTS = jnp.asarray(_rng.uniform(-1, 1, size=(R, 3)), jnp.float32)
DIRECTIONS = POINTS / jnp.linalg.norm(POINTS, axis=-1, keepdims=True)
Z_NEAR, Z_FAR = jnp.full((R,), 0.1), jnp.full((R,), 1.9)
Z = sampling.stratified_samples(Z_NEAR, Z_FAR, N)
WEIGHTS = jnp.full((R, N), 1.0 / N)
SIGMA = jnp.asarray(_rng.uniform(0, 5, size=(R, N)), jnp.float32)

CASES = {
    "lie.hat": (lie.hat, (POINTS,)),
    "lie.vee": (lie.vee, (lie.hat(POINTS),)),
    "lie.so3_exp": (lie.so3_exp, (POINTS,)),
    "lie.so3_log": (lie.so3_log, (T[:, :3, :3],)),
    "lie.se3_exp": (lie.se3_exp, (XI,)),
    "lie.se3_log": (lie.se3_log, (T,)),
    "lie.from_rotation_translation": (lie.from_rotation_translation, (T[:, :3, :3], POINTS)),
    "lie.compose": (lie.compose, (T, T)),
    "lie.invert": (lie.invert, (T,)),
    "lie.apply": (lie.apply, (T, POINTS)),
    "lie.rotate": (lie.rotate, (T, POINTS)),
    "lie.apply_correction": (lie.apply_correction, (XI, T)),
    "encoding.fourier_encode": (lambda x, w: encoding.fourier_encode(x, 4, w), (POINTS, jnp.ones(4))),
    "encoding.fourier_encode exact": (lambda x: encoding.fourier_encode(x, 4, surrogate=False), (POINTS,)),
    "encoding.barf_window": (lambda a: encoding.barf_window(a, 6), (jnp.float32(2.5),)),
    "sampling.slab_intersection": (sampling.slab_intersection, (POINTS * 2, DIRECTIONS)),
    "sampling.cube_interval": (lambda o, d: sampling.cube_interval(o, d, 0.05, 3.0), (POINTS * 2, DIRECTIONS)),
    "sampling.stratified_samples": (lambda a, b, k: sampling.stratified_samples(a, b, N, k), (Z_NEAR, Z_FAR, KEY)),
    "sampling.fine_samples_before": (
        lambda z, w, zn, k: sampling.fine_samples_before(z, w, NF, zn, k),
        (Z, WEIGHTS, Z_NEAR, KEY),
    ),
    "sampling.nerf_resample": (lambda z, w, k: sampling.nerf_resample(z, w, NF, k), (Z, WEIGHTS, KEY)),
    "sampling.merge_samples": (sampling.merge_samples, (Z, Z[:, :3] + 0.01)),
    "rendering.deltas_from_samples": (rendering.deltas_from_samples, (Z, Z_FAR)),
    "rendering.composite": (rendering.composite, (SIGMA, Z, Z_FAR)),
    "rendering.map_range": (rendering.map_range, (WEIGHTS, rendering.deltas_from_samples(Z), Z)),
    "losses.range_l1": (losses.range_l1, (Z[:, 0], Z[:, 1], jnp.ones(R, bool))),
    "losses.termination_index": (losses.termination_index, (Z, Z[:, 3])),
    "losses.termination_loss": (losses.termination_loss, (WEIGHTS, Z, Z[:, 3], jnp.ones(R, bool))),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_public_function_jit_compiles(name):
    function, args = CASES[name]
    out = jax.jit(function)(*args)
    for leaf in jax.tree.leaves(out):
        assert np.all(np.isfinite(np.asarray(leaf, dtype=np.float64))), name
        assert leaf.dtype != jnp.float64  # nothing silently promotes to double


def test_density_field_jit_with_traced_windows():
    field = DensityField(width=16, depth=2, skip_layers=(1,), pos_freqs=4, dir_freqs=2)
    view = jnp.zeros((R, 2))
    params = jax.jit(field.init)(KEY, POINTS, view)

    @jax.jit
    def run(params, alpha):
        return field.apply(params, POINTS, view, encoding.barf_window(alpha, 4), encoding.barf_window(alpha, 2))

    sigma = run(params, jnp.float32(1.5))
    assert sigma.shape == (R,) and np.all(np.asarray(sigma) >= 0)


def test_float32_lie_accuracy_and_zero_gradient():
    np.testing.assert_allclose(jax.jit(lie.se3_log)(T), XI, atol=2e-6)
    jac = jax.jit(jax.jacrev(lambda x: lie.se3_log(lie.se3_exp(x))))(jnp.zeros(6, jnp.float32))
    np.testing.assert_allclose(jac, np.eye(6), atol=1e-6)

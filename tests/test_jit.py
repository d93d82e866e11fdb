"""Every public function of the core modules compiles under jax.jit, in float32 (the training dtype),
with traced arrays wherever the trainer passes them (keys, windows, alpha), and gives finite values."""

import jax
import jax.numpy as jnp
import numpy as np

from neld_jax import lie
from neld_jax.field import encoding, losses, rendering, sampling
from neld_jax.field.density import DensityField

# Inputs built with numpy (float32): no eager JAX work at import.
R, N, NF = 4, 8, 6
KEY = jax.random.key(0)
_rng = np.random.default_rng(0)
XI = (_rng.normal(size=(R, 6)) * 0.3).astype(np.float32)
ROTATIONS = np.linalg.qr(_rng.normal(size=(R, 3, 3)))[0]
ROTATIONS *= np.sign(np.linalg.det(ROTATIONS))[:, None, None]  # -Q has det +1 when Q has det -1 (3x3)
T = np.tile(np.eye(4), (R, 1, 1))
T[:, :3, :3], T[:, :3, 3] = ROTATIONS, _rng.normal(size=(R, 3))
T = T.astype(np.float32)
POINTS = _rng.uniform(-1, 1, size=(R, 3)).astype(np.float32)
DIRECTIONS = POINTS / np.linalg.norm(POINTS, axis=-1, keepdims=True)
Z_NEAR, Z_FAR = np.full((R,), 0.1, np.float32), np.full((R,), 1.9, np.float32)
Z = np.tile(np.linspace(0.15, 1.85, N, dtype=np.float32), (R, 1))
WEIGHTS = np.full((R, N), 1.0 / N, np.float32)
SIGMA = _rng.uniform(0, 5, size=(R, N)).astype(np.float32)
DELTAS = np.full((R, N), 0.2, np.float32)

CASES = {
    "lie.hat": (lie.hat, (POINTS,)),
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
    "encoding.fourier_encode": (lambda x, w: encoding.fourier_encode(x, 4, w), (POINTS, np.ones(4, np.float32))),
    "encoding.fourier_encode exact": (lambda x: encoding.fourier_encode(x, 4, surrogate=False), (POINTS,)),
    "encoding.barf_window": (lambda a: encoding.barf_window(a, 6), (np.float32(2.5),)),
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
    "rendering.map_range": (rendering.map_range, (WEIGHTS, DELTAS, Z)),
    "losses.range_l1": (losses.range_l1, (Z[:, 0], Z[:, 1], np.ones(R, bool))),
    "losses.termination_index": (losses.termination_index, (Z, Z[:, 3])),
    "losses.termination_loss": (losses.termination_loss, (WEIGHTS, Z, Z[:, 3], np.ones(R, bool))),
}


def _run_all_jitted(cases):
    """Every case under one jit with 64-bit types enabled; returns {name: [output leaves]}.

    With x64 off JAX never makes float64, so only with it on does a float64 output reveal a silent promotion
    (a float64 constant, a jnp.zeros without dtype) that would double the cost on a 64-bit-enabled run.
    """
    with jax.enable_x64(True):
        # One jit around all of them: one XLA compile instead of one per function (compiles dominate on a CPU).
        @jax.jit
        def run_all(args):
            return {name: cases[name][0](*args[name]) for name in cases}

        outputs = run_all({name: args for name, (_, args) in cases.items()})
    return {name: jax.tree.leaves(out) for name, out in outputs.items()}


def test_every_public_function_jit_compiles():
    outputs = _run_all_jitted(CASES)
    assert set(outputs) == set(CASES)
    for name, leaves in outputs.items():
        for leaf in leaves:
            assert leaf.dtype != jnp.float64, name  # nothing silently promotes to double
            assert np.all(np.isfinite(np.asarray(leaf, dtype=np.float64))), name


def test_float64_check_catches_a_promotion():
    # The check above is live: a function that adds a default-dtype array does come out float64.
    promoting = {"promotes": (lambda x: x + jnp.zeros(()), (POINTS,)), "keeps": (lambda x: x + 1.0, (POINTS,))}
    outputs = _run_all_jitted(promoting)
    assert outputs["promotes"][0].dtype == jnp.float64
    assert outputs["keeps"][0].dtype == jnp.float32


def test_density_field_jit_with_traced_windows():
    field = DensityField(width=16, depth=2, skip_layers=(1,), pos_freqs=4, dir_freqs=2)
    view = jnp.zeros((R, 3))
    params = jax.jit(field.init)(KEY, POINTS, view)

    @jax.jit
    def run(params, alpha):
        return field.apply(params, POINTS, view, encoding.barf_window(alpha, 4))

    sigma = run(params, jnp.float32(1.5))
    assert sigma.shape == (R,) and np.all(np.asarray(sigma) >= 0)


def test_float32_lie_accuracy_and_zero_gradient():
    np.testing.assert_allclose(jax.jit(lambda x: lie.se3_log(lie.se3_exp(x)))(XI), XI, atol=2e-6)
    jac = jax.jit(jax.jacrev(lambda x: lie.se3_log(lie.se3_exp(x))))(jnp.zeros(6, jnp.float32))
    np.testing.assert_allclose(jac, np.eye(6), atol=1e-6)

"""SE(3)/so(3) maths against jaxlie and scipy, round trips, jacobians vs finite differences, NaN-free gradients.

Every function is jitted once at module level and called on few distinct shapes: on 2 CPU cores the XLA
compiles, not the arithmetic, are what costs time here.
"""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
import scipy.linalg

from neld_jax import lie


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


BATCH = 16
se3_exp = jax.jit(lie.se3_exp)
se3_log = jax.jit(lie.se3_log)
so3_exp = jax.jit(lie.so3_exp)
so3_log = jax.jit(lie.so3_log)


def _flat_log(flat_matrix):
    """se3_log of a 4x4 matrix given as 16 numbers (so finite differences can perturb every entry)."""
    return lie.se3_log(flat_matrix.reshape(4, 4))


def _round_trip(xi):
    return lie.se3_log(lie.se3_exp(xi))


jac_exp = jax.jit(jax.vmap(jax.jacfwd(lie.se3_exp)))
jac_log = jax.jit(jax.vmap(jax.jacfwd(_flat_log)))
jac_round_trip_rev = jax.jit(jax.vmap(jax.jacrev(_round_trip)))


@jax.jit
def _jaxlie_exp(xi):
    return jax.vmap(lambda v: jaxlie.SE3.exp(v).as_matrix())(xi)


@jax.jit
def _jaxlie_log(T):
    return jax.vmap(lambda m: jaxlie.SE3.from_matrix(m).log())(T)


def _random_twists(seed, rotation_scale=1.0, n=BATCH, max_angle=3.0):
    """n random twists; rotation angles scaled by rotation_scale, and kept below max_angle (< pi)."""
    rng = np.random.default_rng(seed)
    xi = rng.normal(size=(n, 6))
    norms = np.linalg.norm(xi[:, 3:], axis=1, keepdims=True)
    xi[:, 3:] *= np.minimum(1.0, max_angle / norms) * rotation_scale
    return xi


def _unit_axes(seed, n=BATCH):
    axes = np.random.default_rng(seed).normal(size=(n, 3))
    return axes / np.linalg.norm(axes, axis=1, keepdims=True)


def _twist_matrix(xi):
    """4x4 element of se(3) whose matrix exponential is exp(xi)."""
    m = np.zeros((4, 4))
    m[:3, :3] = np.asarray(lie.hat(jnp.asarray(xi[3:])))
    m[:3, 3] = xi[:3]
    return m


@pytest.mark.parametrize("rotation_scale", [1.0, 1e-4, 0.0])
def test_exp_and_log_match_jaxlie(rotation_scale):
    xi = _random_twists(0, rotation_scale)
    T = se3_exp(xi)
    np.testing.assert_allclose(T, _jaxlie_exp(xi), atol=1e-14)
    np.testing.assert_allclose(se3_log(T), _jaxlie_log(T), atol=1e-13)
    np.testing.assert_allclose(se3_log(T), xi, atol=1e-13)


def test_exp_and_log_at_tiny_rotation():
    xi = _random_twists(0, 1e-8)
    T = se3_exp(xi)
    # Exact reference: the matrix exponential of the twist.
    expected = np.stack([scipy.linalg.expm(_twist_matrix(v)) for v in xi])
    np.testing.assert_allclose(T, expected, atol=1e-15)
    # jaxlie replaces V by R below theta^2 = 1e-10, an O(theta |rho|) approximation: agree to that order.
    np.testing.assert_allclose(T, _jaxlie_exp(xi), atol=1e-7)
    np.testing.assert_allclose(se3_log(T), xi, rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(se3_log(T), _jaxlie_log(T), atol=1e-7)


def test_exp_matches_matrix_exponential_for_large_rotations():
    xi = _random_twists(1)
    expected = np.stack([scipy.linalg.expm(_twist_matrix(v)) for v in xi])
    np.testing.assert_allclose(se3_exp(xi), expected, atol=1e-13)


def test_log_near_pi():
    axes = _unit_axes(1)
    translations = _random_twists(2)[:, :3]
    for gap in (1e-3, 1e-6, 1e-9):
        omega = axes * (np.pi - gap)
        T = se3_exp(np.concatenate([translations, omega], axis=-1))
        np.testing.assert_allclose(so3_log(T[:, :3, :3]), omega, atol=1e-8)
        np.testing.assert_allclose(se3_log(T), _jaxlie_log(T), atol=1e-6)
        np.testing.assert_allclose(se3_exp(se3_log(T)), T, atol=1e-12)
    # At exactly pi the sign of the axis is ambiguous: the log must still map back to the same rotation.
    R = so3_exp(axes * np.pi)
    omega_back = so3_log(R)
    np.testing.assert_allclose(np.linalg.norm(omega_back, axis=-1), np.pi, atol=1e-12)
    np.testing.assert_allclose(so3_exp(omega_back), R, atol=1e-12)


def test_so3_exp_is_a_rotation_and_matches_se3_block():
    xi = _random_twists(3)
    R = np.asarray(so3_exp(xi[:, 3:]))
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_allclose(se3_exp(xi)[:, :3, :3], R, atol=1e-15)


def test_log_of_exp_round_trip_random_and_tiny():
    xi = _random_twists(4)
    for scale in (1.0, 1e-4, 1e-8):
        np.testing.assert_allclose(se3_log(se3_exp(xi * scale)), xi * scale, rtol=1e-10, atol=1e-15)


def _central_differences(f, points, h):
    """Jacobians [P, out..., in] of the batched f at points [P, in] by central differences."""
    num_points, dim = points.shape
    steps = np.eye(dim) * h
    perturbed = np.concatenate([points[:, None] + steps, points[:, None] - steps], axis=1)  # [P, 2 in, in]
    values = np.asarray(f(perturbed.reshape(-1, dim))).reshape(num_points, 2, dim, -1)
    jac = (values[:, 0] - values[:, 1]) / (2 * h)  # [P, in, out]
    return np.moveaxis(jac, 1, -1)


def test_jacobians_match_finite_differences_including_zero_and_near_pi():
    # Rotation scales 1, 1e-3 and 1e-5, exactly zero, and an angle just below pi.
    xi = _random_twists(5, n=5)
    xi[1, 3:] *= 1e-3
    xi[2, 3:] *= 1e-5
    xi[3] = 0.0
    xi[4, 3:] = _unit_axes(6, 1)[0] * (np.pi - 1e-3)

    analytic = np.asarray(jac_exp(xi))  # [P, 4, 4, 6]
    assert np.all(np.isfinite(analytic))
    numeric = _central_differences(lambda x: se3_exp(x).reshape(len(x), -1), xi, 1e-6).reshape(analytic.shape)
    np.testing.assert_allclose(analytic, numeric, atol=1e-8)

    flat_T = np.asarray(se3_exp(xi)).reshape(len(xi), 16)
    analytic_log = np.asarray(jac_log(flat_T))  # [P, 6, 16]
    assert np.all(np.isfinite(analytic_log))
    numeric_log = _central_differences(lambda m: se3_log(m.reshape(-1, 4, 4)), flat_T, 1e-7)
    np.testing.assert_allclose(analytic_log, numeric_log, atol=1e-5)


def test_gradients_finite_at_exactly_zero():
    zero = np.zeros((5, 6))  # the batch size of the jacobian test above: no new compile
    # d log(exp(xi)) / d xi at zero is the identity, in reverse mode too (the NaN trap of where-branches).
    np.testing.assert_allclose(jac_round_trip_rev(zero)[0], np.eye(6), atol=1e-15)
    # d exp / d omega_z at zero is the generator hat(e_z); d exp / d rho_x is the unit translation.
    jac = np.asarray(jac_exp(zero))[0]
    np.testing.assert_allclose(jac[:3, :3, 5], np.asarray(lie.hat(jnp.array([0.0, 0.0, 1.0]))), atol=1e-15)
    np.testing.assert_allclose(jac[:3, 3, 0], [1.0, 0.0, 0.0], atol=1e-15)
    grad_log = np.asarray(jac_log(np.tile(np.eye(4).reshape(1, 16), (5, 1))))
    assert np.all(np.isfinite(grad_log))


def test_compose_invert_apply_rotate():
    T = np.asarray(se3_exp(_random_twists(7)))
    T_inv = np.asarray(jax.jit(lie.invert)(T))
    np.testing.assert_allclose(lie.compose(T, T_inv), np.broadcast_to(np.eye(4), T.shape), atol=1e-14)
    np.testing.assert_allclose(T_inv, np.linalg.inv(T), atol=1e-12)
    points = np.random.default_rng(8).normal(size=(BATCH, 3))
    homogeneous = np.concatenate([points, np.ones((BATCH, 1))], axis=-1)
    apply = jax.jit(lie.apply)
    np.testing.assert_allclose(apply(T, points), np.einsum("nij,nj->ni", T, homogeneous)[:, :3], atol=1e-14)
    np.testing.assert_allclose(apply(T_inv, apply(T, points)), points, atol=1e-13)
    rotated = jax.jit(lie.rotate)(T, points)
    np.testing.assert_allclose(rotated, np.einsum("nij,nj->ni", T[:, :3, :3], points), atol=1e-14)
    # One transform broadcasts over many points.
    many = np.random.default_rng(9).normal(size=(7, 3))
    np.testing.assert_allclose(lie.apply(T[0], many), many @ T[0, :3, :3].T + T[0, :3, 3], atol=1e-14)


def test_apply_correction_is_right_multiplication():
    xi = _random_twists(10) * 0.1
    T_init = np.asarray(se3_exp(_random_twists(11)))
    corrected = jax.jit(lie.apply_correction)(xi, T_init)
    np.testing.assert_allclose(corrected, T_init @ np.asarray(se3_exp(xi)), atol=1e-14)
    np.testing.assert_allclose(lie.apply_correction(jnp.zeros(6), T_init[0]), T_init[0], atol=1e-15)
    # The correction moves the scan in its own frame: a point is moved by exp(xi) first, then placed by T_init.
    point = np.array([0.3, -0.2, 0.5])
    in_body = np.asarray(lie.apply(se3_exp(xi)[0], point))
    np.testing.assert_allclose(lie.apply(corrected[0], point), lie.apply(T_init[0], in_body), atol=1e-14)


def test_batch_shapes():
    xi = _random_twists(12).reshape(2, 8, 6)
    T = se3_exp(xi)
    assert T.shape == (2, 8, 4, 4)
    assert se3_log(T).shape == (2, 8, 6)
    assert so3_exp(xi[..., 3:]).shape == (2, 8, 3, 3)
    assert so3_log(T[..., :3, :3]).shape == (2, 8, 3)
    np.testing.assert_allclose(se3_log(T), xi, atol=1e-12)


def test_float64_host_helpers_keep_float64_when_x64_is_off():
    """se3_exp_float64 / se3_log_float64 (poses written to files) round-trip a 2.5 km twist and a sub-millimetre
    one to float64 precision even where the process runs float32, and agree with jaxlie."""
    xi = np.array([[2000.0, -1500.0, 30.0, 1e-6, -2e-6, 0.3], [1e-4, 2e-4, -3e-4, 1e-7, 0.0, -1e-7]])
    with jax.enable_x64(False):
        T = lie.se3_exp_float64(xi)
        back = lie.se3_log_float64(T)
    assert T.dtype == np.float64 and back.dtype == np.float64
    np.testing.assert_allclose(back, xi, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(T, jaxlie.SE3.exp(xi).as_matrix(), atol=1e-9)

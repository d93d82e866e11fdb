"""SE(3) and so(3) maths: exponential and logarithm maps, composition, inversion, point transforms.

Everything is pure `jax.numpy`, batched over any leading axes and jit-able (except `se3_exp_float64` /
`se3_log_float64`, host wrappers in float64 for poses written to files). Homogeneous 4x4 matrices are
the pose representation; tangent vectors are 6-vectors in the same order as jaxlie's `SE3`:

    xi = [rho (translation part, 3), omega (rotation part, 3)]

so that `se3_exp(xi)` equals `jaxlie.SE3.exp(xi).as_matrix()`.

Pose convention of the whole project: a scan's pose is a RIGHT correction in the scan's own (body) frame,

    T = apply_correction(xi, T_init) = T_init @ exp(xi),

so `xi` moves the scan relative to where it stands, whatever frame the world is expressed in (a zero `xi` keeps
the initial pose). Why right and not left: docs/method.md, "Poses".

Numerics: the closed forms (sin(t)/t, (1 - cos t)/t^2, ...) are 0/0 at zero rotation. Below a small
angle we switch to Taylor series, and the closed-form branch is evaluated at a harmless substitute angle
(the "safe where" trick), so neither the values nor the gradients ever see a NaN, even at exactly zero.
`so3_log` goes through a unit quaternion (Shepperd's method), which stays accurate near a rotation of pi.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# theta^2 below which the Taylor branches are used. The series below are kept to enough terms that their
# truncation error at this threshold is far below float64 resolution, while the closed forms above it
# lose at most ~eps / theta^2 ~ 1e-12 (float64) to cancellation.
_SMALL_ANGLE_SQ = 1e-4


def hat(omega: jax.Array) -> jax.Array:
    """Skew-symmetric matrix of a 3-vector. omega: [..., 3] -> [..., 3, 3], hat(a) @ b == cross(a, b)."""
    x, y, z = omega[..., 0], omega[..., 1], omega[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([zero, -z, y], axis=-1),
            jnp.stack([z, zero, -x], axis=-1),
            jnp.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )


def _split_small(theta_sq: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(small mask, safe theta^2, safe theta): the safe values replace small angles by 1 (unused there)."""
    small = theta_sq < _SMALL_ANGLE_SQ
    theta_sq_safe = jnp.where(small, jnp.ones_like(theta_sq), theta_sq)
    return small, theta_sq_safe, jnp.sqrt(theta_sq_safe)


def _rodrigues_coefficients(theta_sq: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3 as functions of t^2 (any shape)."""
    small, t2, t = _split_small(theta_sq)
    sin_t = jnp.sin(t)
    half_sinc = jnp.sin(0.5 * t) / (0.5 * t)
    a_closed = sin_t / t
    b_closed = 0.5 * half_sinc**2  # (1 - cos t) / t^2 without cancellation: 1 - cos t = 2 sin^2(t/2)
    c_closed = (t - sin_t) / (t2 * t)
    s = theta_sq
    a_taylor = 1.0 - s / 6.0 + s**2 / 120.0 - s**3 / 5040.0
    b_taylor = 0.5 - s / 24.0 + s**2 / 720.0 - s**3 / 40320.0
    c_taylor = 1.0 / 6.0 - s / 120.0 + s**2 / 5040.0 - s**3 / 362880.0
    return (
        jnp.where(small, a_taylor, a_closed),
        jnp.where(small, b_taylor, b_closed),
        jnp.where(small, c_taylor, c_closed),
    )


def so3_exp(omega: jax.Array) -> jax.Array:
    """Rotation matrix of a rotation vector (Rodrigues). omega: [..., 3] -> R: [..., 3, 3]."""
    theta_sq = jnp.sum(omega**2, axis=-1)
    a, b, _ = _rodrigues_coefficients(theta_sq)
    k = hat(omega)
    eye = jnp.eye(3, dtype=omega.dtype)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def _matrix_to_quaternion(rotation: jax.Array) -> jax.Array:
    """Unit quaternion [..., 4] as (w, x, y, z) of rotation matrices [..., 3, 3] (Shepperd's method).

    Each of the four candidate formulas divides by the square root of one of 1 + tr, 1 + 2 R_ii - tr; these
    four numbers sum to 4, so the largest is >= 1 and the chosen formula is well conditioned. The others
    are evaluated on clamped arguments so that their (discarded) gradients stay finite.
    """
    r = rotation
    r00, r11, r22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    trace = r00 + r11 + r22
    candidates = jnp.stack(
        [1.0 + trace, 1.0 + 2.0 * r00 - trace, 1.0 + 2.0 * r11 - trace, 1.0 + 2.0 * r22 - trace], axis=-1
    )
    best = jnp.argmax(candidates, axis=-1)
    root = jnp.sqrt(jnp.maximum(candidates, 0.25))  # >= 1 wherever it is used
    d21 = r[..., 2, 1] - r[..., 1, 2]
    d02 = r[..., 0, 2] - r[..., 2, 0]
    d10 = r[..., 1, 0] - r[..., 0, 1]
    s21 = r[..., 2, 1] + r[..., 1, 2]
    s02 = r[..., 0, 2] + r[..., 2, 0]
    s10 = r[..., 1, 0] + r[..., 0, 1]
    # One candidate per choice of the largest component c: each stack holds 4 c (w, x, y, z) (e.g. d21 = 4 w x,
    # root_c^2 = 4 c^2), and 2 root_c = 4 c, so the division yields (w, x, y, z).
    q_from_w = jnp.stack([root[..., 0] ** 2, d21, d02, d10], axis=-1) / (2.0 * root[..., 0:1])
    q_from_x = jnp.stack([d21, root[..., 1] ** 2, s10, s02], axis=-1) / (2.0 * root[..., 1:2])
    q_from_y = jnp.stack([d02, s10, root[..., 2] ** 2, s21], axis=-1) / (2.0 * root[..., 2:3])
    q_from_z = jnp.stack([d10, s02, s21, root[..., 3] ** 2], axis=-1) / (2.0 * root[..., 3:4])
    options = jnp.stack([q_from_w, q_from_x, q_from_y, q_from_z], axis=-2)  # [..., 4 choices, 4]
    quat = jnp.take_along_axis(options, best[..., None, None], axis=-2)[..., 0, :]
    return quat / jnp.linalg.norm(quat, axis=-1, keepdims=True)


def so3_log(rotation: jax.Array) -> jax.Array:
    """Rotation vector of a rotation matrix, angle in [0, pi]. rotation: [..., 3, 3] -> omega: [..., 3]."""
    quat = _matrix_to_quaternion(rotation)
    # q and -q are the same rotation; w >= 0 puts the angle 2 atan2(|v|, w) in [0, pi].
    quat = jnp.where(quat[..., :1] < 0, -quat, quat)
    w, v = quat[..., 0], quat[..., 1:]
    n_sq = jnp.sum(v**2, axis=-1)
    small = n_sq < _SMALL_ANGLE_SQ
    n_safe = jnp.sqrt(jnp.where(small, jnp.ones_like(n_sq), n_sq))
    scale_closed = 2.0 * jnp.arctan2(n_safe, w) / n_safe
    # Small |v| means w ~ 1 (w >= 0): 2 atan(n / w) / n = (2 / w)(1 - r/3 + r^2/5 - r^3/7), r = (n / w)^2.
    w_safe = jnp.where(small, w, jnp.ones_like(w))  # w may be 0 (angle pi) where this branch is unused
    ratio_sq = n_sq / w_safe**2
    scale_taylor = (2.0 / w_safe) * (1.0 - ratio_sq / 3.0 + ratio_sq**2 / 5.0 - ratio_sq**3 / 7.0)
    scale = jnp.where(small, scale_taylor, scale_closed)
    return scale[..., None] * v


def _left_jacobian_inverse(omega: jax.Array) -> jax.Array:
    """V^-1 for se3_log: I - K/2 + D K^2 with D = (1 - (t/2) cot(t/2)) / t^2. omega: [..., 3] -> [..., 3, 3]."""
    theta_sq = jnp.sum(omega**2, axis=-1)
    small, t2, t = _split_small(theta_sq)
    half = 0.5 * t
    d_closed = (1.0 - half * jnp.cos(half) / jnp.sin(half)) / t2
    s = theta_sq
    d_taylor = 1.0 / 12.0 + s / 720.0 + s**2 / 30240.0 + s**3 / 1209600.0
    d = jnp.where(small, d_taylor, d_closed)
    k = hat(omega)
    eye = jnp.eye(3, dtype=omega.dtype)
    return eye - 0.5 * k + d[..., None, None] * (k @ k)


def se3_exp(xi: jax.Array) -> jax.Array:
    """Homogeneous matrix of a twist xi = [rho, omega]. xi: [..., 6] -> T: [..., 4, 4]."""
    rho, omega = xi[..., :3], xi[..., 3:]
    theta_sq = jnp.sum(omega**2, axis=-1)
    a, b, c = _rodrigues_coefficients(theta_sq)
    k = hat(omega)
    k2 = k @ k
    eye = jnp.eye(3, dtype=xi.dtype)
    rotation = eye + a[..., None, None] * k + b[..., None, None] * k2
    v = eye + b[..., None, None] * k + c[..., None, None] * k2
    translation = jnp.einsum("...ij,...j->...i", v, rho)
    return from_rotation_translation(rotation, translation)


def se3_log(transform: jax.Array) -> jax.Array:
    """Twist [rho, omega] of a homogeneous matrix (rotation angle in [0, pi]). T: [..., 4, 4] -> [..., 6]."""
    omega = so3_log(transform[..., :3, :3])
    rho = jnp.einsum("...ij,...j->...i", _left_jacobian_inverse(omega), transform[..., :3, 3])
    return jnp.concatenate([rho, omega], axis=-1)


def from_rotation_translation(rotation: jax.Array, translation: jax.Array) -> jax.Array:
    """rotation: [..., 3, 3], translation: [..., 3] -> homogeneous [..., 4, 4]."""
    batch = jnp.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    rotation = jnp.broadcast_to(rotation, batch + (3, 3))
    translation = jnp.broadcast_to(translation, batch + (3,))
    top = jnp.concatenate([rotation, translation[..., None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], dtype=top.dtype), batch + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def compose(a: jax.Array, b: jax.Array) -> jax.Array:
    """a @ b: apply b first, then a. a, b: [..., 4, 4] (broadcasting) -> [..., 4, 4]."""
    return a @ b


def invert(transform: jax.Array) -> jax.Array:
    """Closed-form inverse [R^T, -R^T t; 0, 1]. T: [..., 4, 4] -> [..., 4, 4]."""
    rotation_t = jnp.swapaxes(transform[..., :3, :3], -1, -2)
    translation = -jnp.einsum("...ij,...j->...i", rotation_t, transform[..., :3, 3])
    return from_rotation_translation(rotation_t, translation)


def apply(transform: jax.Array, points: jax.Array) -> jax.Array:
    """R p + t. transform: [..., 4, 4], points: [..., 3] -> [..., 3].

    Leading axes broadcast like numpy (right-aligned): one [4, 4] applies to points [N, 3]; per-scan poses
    [S, 4, 4] with points [S, N, 3] need transform[:, None].
    """
    return rotate(transform, points) + transform[..., :3, 3]


def rotate(transform: jax.Array, vectors: jax.Array) -> jax.Array:
    """R v (rotation only, for directions). transform: [..., 4, 4], vectors: [..., 3] -> [..., 3] (as `apply`)."""
    return jnp.einsum("...ij,...j->...i", transform[..., :3, :3], vectors)


def apply_correction(xi: jax.Array, T_init: jax.Array) -> jax.Array:
    """The project's pose convention: T_init @ exp(xi), a right correction in the scan's body frame.

    xi: [..., 6] twists [rho, omega], T_init: [..., 4, 4] -> corrected poses [..., 4, 4].
    """
    return compose(T_init, se3_exp(xi))


def se3_exp_float64(xi) -> np.ndarray:
    """`se3_exp` in float64 whatever jax_enable_x64 says, on host arrays: for poses written to files and judged
    (centimetre corrections on kilometre routes need more than float32's 7 digits). xi: [..., 6] -> [..., 4, 4]."""
    with jax.enable_x64(True):
        return np.asarray(se3_exp(jnp.asarray(xi, jnp.float64)))


def se3_log_float64(transform) -> np.ndarray:
    """`se3_log` in float64 on host arrays (as `se3_exp_float64`). transform: [..., 4, 4] -> [..., 6]."""
    with jax.enable_x64(True):
        return np.asarray(se3_log(jnp.asarray(transform, jnp.float64)))

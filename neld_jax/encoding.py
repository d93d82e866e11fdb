"""Fourier positional encoding with the surrogate gradient (eq. 9) and BARF's coarse-to-fine window.

    gamma(x) = [x, cos(2^k pi x) for k < L, sin(2^k pi x) for k < L]

Output layout for x: [..., D]: first the D identity features, then the L*D cosines (k-major: all D inputs
of frequency 0, then of frequency 1, ...), then the L*D sines in the same order: [..., D * (1 + 2L)].

The surrogate gradient keeps the forward pass but divides the backward pass of frequency k by 2^k pi:
d/dx cos(2^k pi x) -> -sin(2^k pi x) and d/dx sin(2^k pi x) -> cos(2^k pi x). It is exactly the gradient of
gamma_k(x) / (2^k pi), so a pose gradient that flows through high frequencies is not amplified by 2^k pi.
Being a custom VJP, the surrogate supports reverse-mode differentiation only (grad, vjp, jacrev); use
surrogate=False where forward mode (jvp, jacfwd) is needed.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp


def encoded_dim(in_dim: int, num_freqs: int) -> int:
    """Width of `fourier_encode`'s output for `in_dim` inputs and `num_freqs` frequencies."""
    return in_dim * (1 + 2 * num_freqs)


# Taylor coefficients of sin(theta) / theta and cos(theta) in theta^2, enough terms for float64 on |theta| <= pi/4.
_SIN_COEFFS = tuple((-1) ** i / math.factorial(2 * i + 1) for i in range(9))
_COS_COEFFS = tuple((-1) ** i / math.factorial(2 * i) for i in range(10))


def _polynomial(coeffs: tuple, x: jax.Array) -> jax.Array:
    """sum_i coeffs[i] x^i by Horner's rule."""
    acc = jnp.full_like(x, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        acc = acc * x + c
    return acc


def sin_cos_pi(t: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(sin(pi t), cos(pi t)), elementwise, from multiply/add/select only.

    XLA:CPU evaluates jnp.sin/jnp.cos ~15x slower than this. The range reduction is exact: t = q/2 + r with
    integer q and |r| <= 1/4 (exact in floating point for |t| < 2^22), then Taylor series on pi r in
    [-pi/4, pi/4] (float64-accurate) and the quadrant q mod 4 picks the signs. Error ~1 ulp at any t, where
    jnp.sin(2^k pi x) first rounds the product 2^k pi x (error up to 2^k pi ulp: 1e-4 at k = 9 in float32).
    """
    q = jnp.round(2.0 * t)
    theta = jnp.pi * (t - 0.5 * q)
    theta_sq = theta * theta
    s = theta * _polynomial(_SIN_COEFFS, theta_sq)
    c = _polynomial(_COS_COEFFS, theta_sq)
    quadrant = q.astype(jnp.int32) & 3  # two's complement: also right for negative q
    sin = jnp.where(quadrant == 0, s, jnp.where(quadrant == 1, c, jnp.where(quadrant == 2, -s, -c)))
    cos = jnp.where(quadrant == 0, c, jnp.where(quadrant == 1, -s, jnp.where(quadrant == 2, -c, s)))
    return sin, cos


def _half_turns(x: jax.Array, num_freqs: int) -> jax.Array:
    """2^k x for k < L, k-major (exact: power-of-two scales). x: [..., D] -> [..., L*D]; angles are pi times this."""
    scales = 2.0 ** jnp.arange(num_freqs, dtype=x.dtype)  # [L]
    scaled = scales[:, None] * x[..., None, :]  # [..., L, D]
    return scaled.reshape(*x.shape[:-1], num_freqs * x.shape[-1])


def _cos_sin(x: jax.Array, num_freqs: int) -> tuple[jax.Array, jax.Array]:
    sin, cos = sin_cos_pi(_half_turns(x, num_freqs))
    return cos, sin


@partial(jax.custom_vjp, nondiff_argnums=(1,))
def _cos_sin_surrogate(x: jax.Array, num_freqs: int) -> tuple[jax.Array, jax.Array]:
    """Same values as `_cos_sin`; the backward pass is that of gamma_k / (2^k pi)."""
    return _cos_sin(x, num_freqs)


def _cos_sin_surrogate_fwd(x, num_freqs):
    cos, sin = _cos_sin(x, num_freqs)
    return (cos, sin), (cos, sin)


def _cos_sin_surrogate_bwd(num_freqs, residuals, cotangents):
    cos, sin = residuals
    g_cos, g_sin = cotangents
    per_feature = -g_cos * sin + g_sin * cos  # [..., L*D]
    in_dim = cos.shape[-1] // num_freqs
    x_bar = per_feature.reshape(*cos.shape[:-1], num_freqs, in_dim).sum(axis=-2)
    return (x_bar,)


_cos_sin_surrogate.defvjp(_cos_sin_surrogate_fwd, _cos_sin_surrogate_bwd)


def fourier_encode(
    x: jax.Array,
    num_freqs: int,
    window: jax.Array | None = None,
    surrogate: bool = True,
) -> jax.Array:
    """gamma(x) with optional per-frequency window and surrogate backward pass.

    x: [..., D]; num_freqs: L (static); window: [L] weights of each frequency (BARF), treated as a constant
    (no gradient flows into it); surrogate: divide frequency k's backward pass by 2^k pi (eq. 9); False
    gives the exact gradient (the ablation). Returns [..., D * (1 + 2L)] laid out as [x, cos, sin].
    """
    if num_freqs == 0:
        return x
    cos, sin = _cos_sin_surrogate(x, num_freqs) if surrogate else _cos_sin(x, num_freqs)
    if window is not None:
        weights = jnp.repeat(jax.lax.stop_gradient(window).astype(x.dtype), x.shape[-1])  # [L*D], k-major
        cos, sin = cos * weights, sin * weights
    return jnp.concatenate([x, cos, sin], axis=-1)


def barf_window(alpha: jax.Array | float, num_freqs: int) -> jax.Array:
    """BARF's coarse-to-fine weights w_k = (1 - cos(pi clip(alpha - k, 0, 1))) / 2, k < L.

    alpha: scalar, may be traced (0: every frequency off, L: every frequency fully on) -> [L].
    """
    k = jnp.arange(num_freqs, dtype=jnp.result_type(alpha, jnp.float32))
    return 0.5 * (1.0 - jnp.cos(jnp.pi * jnp.clip(alpha - k, 0.0, 1.0)))

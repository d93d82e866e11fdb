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
import numpy as np

# Taylor coefficients of sin(theta) / theta in theta^2: float64-accurate on |theta| <= pi/2 (the last term
# dropped, (pi/2)^25 / 25!, is ~1e-20).
_SIN_COEFFS = tuple((-1) ** i / math.factorial(2 * i + 1) for i in range(12))


def _polynomial(coeffs: tuple, x: jax.Array) -> jax.Array:
    """sum_i coeffs[i] x^i by Horner's rule."""
    acc = jnp.full_like(x, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        acc = acc * x + c
    return acc


@jax.custom_jvp
def sin_pi(t: jax.Array) -> jax.Array:
    """sin(pi t), elementwise, from multiply/add/select only; cos(pi t) is sin_pi(t + 0.5).

    XLA:CPU evaluates jnp.sin/jnp.cos several times slower than this, and one sine over the stacked cosine and
    sine angles fuses into one loop (separate sin and cos outputs made XLA fuse, and so compute, the whole
    polynomial twice). The range reduction is exact: t = q + r with integer q and |r| <= 1/2 (exact in
    floating point), then a Taylor series on pi r in [-pi/2, pi/2] and the sign (-1)^q. Error ~1 ulp at any t,
    where jnp.sin(2^k pi x) first rounds the product 2^k pi x (error up to 2^k pi ulp: 1e-4 at k = 9 in float32).
    """
    q = jnp.round(t)
    theta = jnp.pi * (t - q)
    s = theta * _polynomial(_SIN_COEFFS, theta * theta)
    odd = (q.astype(jnp.int32) & 1) == 1  # two's complement: also right for negative q; |q| < 2^31 here
    return jnp.where(odd, -s, s)


@sin_pi.defjvp
def _sin_pi_jvp(primals, tangents):
    (t,), (t_dot,) = primals, tangents
    return sin_pi(t), jnp.pi * sin_pi(t + 0.5) * t_dot


def _half_turns(x: jax.Array, num_freqs: int) -> jax.Array:
    """2^k x for k < L, k-major (exact: power-of-two scales). x: [..., D] -> [..., L*D]; angles are pi times this."""
    scales = 2.0 ** jnp.arange(num_freqs, dtype=x.dtype)  # [L]
    scaled = scales[:, None] * x[..., None, :]  # [..., L, D]
    return scaled.reshape(*x.shape[:-1], num_freqs * x.shape[-1])


def _cos_sin(x: jax.Array, num_freqs: int) -> jax.Array:
    """[cos(pi 2^k x), sin(pi 2^k x)] stacked on the last axis: x [..., D] -> [..., 2*L*D] (cosines first).

    cos(pi t) = sin(pi (t + 1/2)); the shift rounds by at most half an ulp of t + 1/2, no more than one ulp of
    t: below the resolution of t itself (2^k times that of x).
    """
    t = _half_turns(x, num_freqs)
    return sin_pi(jnp.concatenate([t + 0.5, t], axis=-1))


@partial(jax.custom_vjp, nondiff_argnums=(1,))
def _cos_sin_surrogate(x: jax.Array, num_freqs: int) -> jax.Array:
    """Same values as `_cos_sin`; the backward pass is that of gamma_k / (2^k pi)."""
    return _cos_sin(x, num_freqs)


def _cos_sin_surrogate_fwd(x, num_freqs):
    values = _cos_sin(x, num_freqs)
    return values, values


def _cos_sin_surrogate_bwd(num_freqs, values, cotangent):
    n = values.shape[-1] // 2  # L*D
    cos, sin = values[..., :n], values[..., n:]
    per_feature = -cotangent[..., :n] * sin + cotangent[..., n:] * cos  # [..., L*D]
    x_bar = per_feature.reshape(*values.shape[:-1], num_freqs, n // num_freqs).sum(axis=-2)
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
    cos_sin = _cos_sin_surrogate(x, num_freqs) if surrogate else _cos_sin(x, num_freqs)  # [..., 2*L*D]
    if window is not None:
        # The per-feature weights [2*L*D] as window @ (0/1 expansion matrix) rather than repeat/tile: XLA never
        # fuses a dot into an elementwise loop, so the few weights are computed once. A broadcast would be
        # fused, and the window's cosine evaluated again for every sample (9 ms of a 240 ms CPU step).
        expansion = np.kron(np.eye(num_freqs), np.ones((1, x.shape[-1])))  # [L, L*D]
        expansion = np.concatenate([expansion, expansion], axis=1).astype(x.dtype)  # [L, 2*L*D]
        weights = jnp.dot(
            jax.lax.stop_gradient(window).astype(x.dtype), expansion, precision=jax.lax.Precision.HIGHEST
        )  # full float32 on GPUs too (no TF32)
        cos_sin = cos_sin * weights
    return jnp.concatenate([x, cos_sin], axis=-1)


def barf_window(alpha: jax.Array | float, num_freqs: int) -> jax.Array:
    """BARF's coarse-to-fine weights w_k = (1 - cos(pi clip(alpha - k, 0, 1))) / 2, k < L.

    alpha: scalar, may be traced (0: every frequency off, L: every frequency fully on) -> [L].
    """
    k = jnp.arange(num_freqs, dtype=jnp.result_type(alpha, jnp.float32))
    return 0.5 * (1.0 - jnp.cos(jnp.pi * jnp.clip(alpha - k, 0.0, 1.0)))

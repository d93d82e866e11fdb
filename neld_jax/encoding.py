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

from functools import partial

import jax
import jax.numpy as jnp


def encoded_dim(in_dim: int, num_freqs: int) -> int:
    """Width of `fourier_encode`'s output for `in_dim` inputs and `num_freqs` frequencies."""
    return in_dim * (1 + 2 * num_freqs)


def _angles(x: jax.Array, num_freqs: int) -> jax.Array:
    """2^k pi x for k < L, k-major. x: [..., D] -> [..., L*D]."""
    scales = (2.0 ** jnp.arange(num_freqs, dtype=x.dtype)) * jnp.pi  # [L]
    scaled = scales[:, None] * x[..., None, :]  # [..., L, D]
    return scaled.reshape(*x.shape[:-1], num_freqs * x.shape[-1])


def _cos_sin(x: jax.Array, num_freqs: int) -> tuple[jax.Array, jax.Array]:
    angles = _angles(x, num_freqs)
    return jnp.cos(angles), jnp.sin(angles)


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

"""Training losses on rendered rays: the L1 range loss (eq. 10) and the termination loss (eqs. 11-12).

The termination loss is KL(h* || h_hat) with the pseudo-Dirac target h* that puts all mass on the first
sample beyond the measured range. With 0 ln 0 = 0 this reduces to -ln h_hat(z_{n*}); the paper prints the
KL with its sign flipped, the quantity minimised here is the (non-negative) negative log-likelihood.
Masked means divide by the number of rays that count (at least 1), so an all-masked batch gives 0.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _masked_mean(values: jax.Array, mask: jax.Array | None) -> jax.Array:
    """Mean of values [R] over mask [R] (bool or 0/1); masked-out entries may hold NaN without harm."""
    if mask is None:
        return jnp.mean(values)
    mask = mask.astype(bool)
    total = jnp.sum(jnp.where(mask, values, 0.0))
    return total / jnp.maximum(jnp.sum(mask), 1).astype(values.dtype)


def range_l1(pred: jax.Array, target: jax.Array, mask: jax.Array | None = None) -> jax.Array:
    """Mean |pred - target| over the rays in mask. pred, target: [R], mask: [R] or None -> scalar."""
    return _masked_mean(jnp.abs(pred - target), mask)


def termination_index(z: jax.Array, target: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Index n* of the first sample beyond the measured range (eq. 12).

    z: [R, N] sorted, target: [R] -> (idx [R] int, valid [R] bool); valid is False (and idx 0) when no
    sample lies beyond the target.
    """
    beyond = z > target[:, None]
    return jnp.argmax(beyond, axis=-1), jnp.any(beyond, axis=-1)


def termination_loss(
    weights: jax.Array,
    z: jax.Array,
    target: jax.Array,
    mask: jax.Array | None = None,
    eps: float = 1e-10,
) -> jax.Array:
    """Mean over valid (and masked-in) rays of -ln(max(h[n*], eps)).

    weights: [R, N] termination weights h, z: [R, N] their sorted ranges, target: [R] measured ranges,
    mask: [R] or None. eps guards ln 0 (the loss of a ray is at most -ln eps). Returns a scalar.
    """
    idx, valid = termination_index(z, target)
    h_star = jnp.take_along_axis(weights, idx[:, None], axis=-1)[:, 0]
    nll = -jnp.log(jnp.maximum(h_star, eps))
    use = valid if mask is None else valid & mask.astype(bool)
    return _masked_mean(nll, use)

"""Alpha compositing of densities along rays (eqs. 2-3) and the map range of a ray (eq. 14).

    h_i = exp(-sum_{j<i} sigma_j delta_j) * (1 - exp(-sigma_i delta_i)),     D_hat = sum_i h_i z_i

Built for densities anywhere from 0 to ~1e10: alpha uses -expm1 (accurate for tiny sigma delta), the
transmittance is the exp of an exclusive cumulative sum (never a product of many factors, never a
difference of large sums), so values and gradients stay finite.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class Rendered(NamedTuple):
    """Result of `composite` for R rays of N samples."""

    weights: jax.Array  # h: [R, N] termination probability of each sample
    depth: jax.Array  # expected range sum_i h_i z_i: [R] (not normalised by the opacity, eq. 2)
    opacity: jax.Array  # sum_i h_i: [R], in [0, 1]
    deltas: jax.Array  # [R, N] sample spacings used


def deltas_from_samples(z: jax.Array, z_far: jax.Array | None = None) -> jax.Array:
    """Spacings delta_i = z_{i+1} - z_i. z: [R, N] sorted; z_far: [R] or None -> [R, N].

    The last spacing is max(z_far - z_N, 0) when z_far is given, else a copy of the one before it.
    """
    inner = z[..., 1:] - z[..., :-1]
    if z_far is not None:
        last = jnp.maximum(z_far[..., None] - z[..., -1:], 0.0)
    elif z.shape[-1] >= 2:
        last = inner[..., -1:]
    else:
        raise ValueError("deltas_from_samples needs z_far when there is a single sample per ray")
    return jnp.concatenate([inner, last], axis=-1)


def composite(sigma: jax.Array, z: jax.Array, z_far: jax.Array | None = None) -> Rendered:
    """Termination weights and expected range of each ray.

    sigma: [R, N] densities (>= 0) at the samples z: [R, N] (sorted); z_far: [R] end of the interval, used
    for the last spacing. Returns `Rendered` (weights [R, N], depth [R], opacity [R], deltas [R, N]).
    """
    deltas = deltas_from_samples(z, z_far)
    optical = sigma * deltas  # [R, N], sigma_i delta_i
    alpha = -jnp.expm1(-optical)  # 1 - exp(-x), accurate for small x
    # Exclusive cumulative sum: the optical depth in front of sample i (0 for the first sample).
    in_front = jnp.concatenate([jnp.zeros_like(optical[..., :1]), jnp.cumsum(optical[..., :-1], axis=-1)], axis=-1)
    weights = jnp.exp(-in_front) * alpha
    depth = jnp.sum(weights * z, axis=-1)
    opacity = jnp.sum(weights, axis=-1)
    return Rendered(weights=weights, depth=depth, opacity=opacity, deltas=deltas)


def map_range(weights: jax.Array, deltas: jax.Array, z: jax.Array) -> jax.Array:
    """Eq. 14: the range z_i of the sample with the largest termination density h_i / delta_i.

    weights, deltas, z: [R, N] -> [R]. A sample with delta_i = 0 has h_i = 0 and scores 0.
    """
    positive = deltas > 0
    density = jnp.where(positive, weights / jnp.where(positive, deltas, 1.0), 0.0)
    best = jnp.argmax(density, axis=-1)
    return jnp.take_along_axis(z, best[..., None], axis=-1)[..., 0]

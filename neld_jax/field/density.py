"""The density field: an MLP from (position, view direction) to a non-negative density sigma.

Architecture after NeRF in the Wild (as NeLD-BA uses it): Fourier-encoded position -> `depth` dense ReLU
layers of `width`, with the encoded position concatenated again to the input of each layer listed in
`skip_layers` -> features; density head: concat(features, encoded view direction) -> dense ReLU of
width // 2 -> dense 1 -> softplus. Both encodings use the surrogate gradient (eq. 9) unless `surrogate` is False.

View directions are world-frame unit vectors [..., 3], encoded as they are (their components already lie in
[-1, 1] like the normalised positions). Not azimuth/elevation angles: their Jacobian is infinite at a vertical
ray, which fed NaN or huge values into the pose gradients of LiDARs that see straight up or down
(docs/method.md, "The field").
"""

from __future__ import annotations

import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from neld_jax.field.encoding import fourier_encode
from neld_jax.field.options import MATMUL_DTYPES


def bfloat16_dot_general(lhs, rhs, dimension_numbers, precision=None, preferred_element_type=None):
    """lax.dot_general on bfloat16 copies of both operands, accumulated and returned in float32.

    The parameters stay float32 (Adam updates them in float32); only the matmul's inputs are rounded, to the
    8-bit mantissa of bfloat16 (a relative error of up to 2^-9 per input).
    """
    del preferred_element_type
    return jax.lax.dot_general(
        lhs.astype(jnp.bfloat16),
        rhs.astype(jnp.bfloat16),
        dimension_numbers,
        precision=precision,
        preferred_element_type=jnp.float32,
    )


def _inverse_softplus(value: float) -> float:
    """Pre-activation b with softplus(b) == value (value > 0)."""
    return math.log(math.expm1(value))


class DensityField(nn.Module):
    """sigma(x, d). Call with positions [..., 3], view_dirs [..., 3] unit vectors -> sigma [...] (>= 0).

    pos_window: [pos_freqs] are the BARF coarse-to-fine weights of the position encoding (None: all on); the
    view direction's frequencies are always all on.
    `skip_layers` are the indices (0-based) of hidden layers whose input gets the encoded position again.
    `initial_density` is the density the untrained field outputs, approximately (see the output bias).
    `matmul_dtype`: "float32", or "bfloat16" for the hidden layers' matmuls on bfloat16 inputs with float32
    parameters and accumulation (`bfloat16_dot_general`; the tiny output layer stays float32).
    """

    width: int = 512
    depth: int = 8
    skip_layers: tuple = (4,)
    pos_freqs: int = 15
    dir_freqs: int = 4
    surrogate: bool = True
    dtype: Any = jnp.float32
    initial_density: float = 0.1
    matmul_dtype: str = "float32"

    @nn.compact
    def __call__(
        self,
        positions: jax.Array,
        view_dirs: jax.Array,
        pos_window: jax.Array | None = None,
    ) -> jax.Array:
        if self.matmul_dtype not in MATMUL_DTYPES:
            raise ValueError(f"matmul_dtype must be one of {MATMUL_DTYPES}, got {self.matmul_dtype!r}")
        dot = bfloat16_dot_general if self.matmul_dtype == "bfloat16" else None
        positions = positions.astype(self.dtype)
        encoded = fourier_encode(positions, self.pos_freqs, pos_window, surrogate=self.surrogate)
        hidden = encoded
        for layer in range(self.depth):
            if layer in self.skip_layers:
                hidden = jnp.concatenate([hidden, encoded], axis=-1)
            hidden = nn.relu(nn.Dense(self.width, dtype=self.dtype, dot_general=dot, name=f"hidden_{layer}")(hidden))

        encoded_dir = fourier_encode(view_dirs.astype(self.dtype), self.dir_freqs, surrogate=self.surrogate)
        hidden = jnp.concatenate([hidden, encoded_dir], axis=-1)
        hidden = nn.relu(nn.Dense(self.width // 2, dtype=self.dtype, dot_general=dot, name="density_hidden")(hidden))

        # The untrained field should be nearly transparent but not empty: a zero density (a ReLU below 0)
        # gives no termination weights and so no gradients, and a large one hides everything behind the
        # first sample. A small output kernel and a bias at softplus^-1(initial_density) start every
        # point close to initial_density.
        output = nn.Dense(
            1,
            dtype=self.dtype,
            kernel_init=nn.initializers.variance_scaling(1e-4, "fan_in", "truncated_normal"),
            bias_init=nn.initializers.constant(_inverse_softplus(self.initial_density)),
            name="density_out",
        )(hidden)
        return jax.nn.softplus(output[..., 0])


def field_from_config(model_cfg) -> DensityField:
    """The DensityField that `model_cfg` (config.model) describes, with every architecture field of it.

    A Flax module is a frozen, hashable dataclass: build it once and pass it as a static jit argument.
    """
    return DensityField(
        width=int(model_cfg.width),
        depth=int(model_cfg.depth),
        skip_layers=tuple(int(k) for k in model_cfg.skip_layers),
        pos_freqs=int(model_cfg.pos_freqs),
        dir_freqs=int(model_cfg.dir_freqs),
        surrogate=bool(model_cfg.surrogate_gradient),
        matmul_dtype=str(model_cfg.matmul_dtype),
    )

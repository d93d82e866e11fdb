"""Each step's ray batch (train.sample_batch), uniform over all rays."""

import jax
import jax.numpy as jnp
import numpy as np

from neld_jax import train
from neld_jax.data.rays import RaySet


def test_uniform_batches_cover_every_ray_and_jit():
    scan_index = np.repeat(np.arange(2), 5).astype(np.int32)
    rays = train.device_rays(RaySet(np.tile([[1.0, 0, 0]], (10, 1)).astype(np.float32),
                                    np.ones(10, np.float32), scan_index))
    sample = jax.jit(train.sample_batch, static_argnums=(2, 3))
    indices = sample(jax.random.PRNGKey(0), rays, 20000, 0)
    assert indices.shape == (20000,) and indices.dtype == jnp.int32
    counts = np.bincount(np.asarray(indices), minlength=10)
    assert counts.min() > 1700 and counts.max() < 2300 and np.asarray(indices).max() == 9

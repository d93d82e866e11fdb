"""neld-jax: Neural LiDAR Bundle Adjustment (NeLD-BA) in JAX/Flax.

Pure building blocks live in `lie`, `encoding`, `sampling`, `rendering`, `losses` and `field`;
data handling in `neld_jax.data`; training, mapping and evaluation at the edges.
"""

__version__ = "0.1.0"

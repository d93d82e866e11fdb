"""Reading LiDAR sequences: one loader module per layout behind a small registry, the in-memory `Sequence` they
return, preprocessing (keyframes, range crop, voxel grid), the normalisation into the cube, rays, and the
synthetic generator. Imports nothing of the rest of the package but `errors` and `geometry`.

`load_keyframes(config.data)` is the one call a run makes: every input scan as read, and the keyframes it trains on.
"""

from neld_jax.data.preprocess import load_preprocessed as load_keyframes  # noqa: F401

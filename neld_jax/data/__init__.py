"""Data handling at the edge of the library (imports Open3D and SciPy; the core does not import this package):

- `scans`, `poses`: scan and trajectory formats (PCD/PLY/KITTI .bin/.npy; TUM, KITTI, Newer College CSV);
- `sequence`: the in-memory `Sequence` every loader returns, timestamp matching, pose-jump checks;
- `datasets`, `lio_keyframes`: loaders of the layouts in docs/design.md;
- `preprocess`: keyframes, range crop, voxel grid; `normalize`: the [-1, 1]^3 cube; `rays`: training rays;
- `synthetic`: a seeded synthetic sequence with exact ground truth; `pseudo_gt`: drifted copies of real ones.

Import the module you need (`from neld_jax.data.datasets import load_sequence`); this package file imports
nothing, so that `import neld_jax.data.poses` stays light.
"""

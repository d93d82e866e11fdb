"""Data handling, the library's lowest layer besides `neld_jax.errors` and `neld_jax.geometry` (nothing here
imports any other neld_jax module):

- `scans`, `poses`: scan and trajectory formats (PCD/PLY/KITTI .bin/.npy; TUM, KITTI, Newer College CSV);
- `sequence`: the in-memory `Sequence` every loader returns, pose-jump checks;
- `timing`: timestamp files, nearest-time lookup, matching scans to poses by time;
- `formats`: the registry of formats and `load_sequence(config.data)`; one module per format: `generic`,
  `fusionportable`, `newer_college`, `lio_keyframes`, `hba`, `kitti`, `synthetic` (also the generator's defaults);
  `layout`: what the folder formats share; `ground_truth`: explicit paths and published frame offsets;
  `frames`: scans and poses in the expected frames; `sweep_times`: per-point times of raw sweeps from azimuths;
- `preprocess`: keyframes, range crop, voxel grid, and `load_keyframes(config.data)`, what a run reads;
  `normalize`: the [-1, 1]^3 cube; `rays`: training rays;
- `pseudo_gt`: drifted copies of real sequences; `rosbag_import`: rosbags into the generic layout.

Most modules import Open3D or SciPy. The core (model, trainer, mapping, metrics, config) imports only
`timing` (metrics), `synthetic` for its defaults (config) and `sequence`, which import neither when loaded.
Import the module you need (`from neld_jax.data.preprocess import load_keyframes`); this package file imports
nothing, so that `import neld_jax.data.poses` stays light.
"""

"""Reading what is on disk, and nothing else: scan and trajectory files, the dataset layouts, the in-memory
`Sequence`, keyframe selection. No module here runs a registration (the front-end, `neld_jax.frontend`) or makes
scans up (`neld_jax.synthetic`); besides `neld_jax.errors` and `neld_jax.geometry` nothing here imports any other
neld_jax module.

- `scans`, `poses`: scan and trajectory formats (PCD/PLY/KITTI .bin/.npy; TUM, KITTI, Newer College CSV);
- `sequence`: the in-memory `Sequence` every loader returns, pose-jump checks; `scan_source`: scans read when used;
- `timing`: timestamp files, nearest-time lookup, matching scans to poses by time;
- `formats`: the registry of folder formats and `read_sequence(config.data)`; one module per format: `generic`,
  `fusionportable`, `newer_college`, `lio_keyframes`, `hba`, `kitti`; `layout`: what the folder formats share;
  `ground_truth`: explicit paths and published frame offsets; `frames`: scans and poses in the expected frames;
- `preprocess`: keyframes, range crop, voxel grid; `sessions`: several recordings of one place joined;
- `bags`: rosbags without ROS (`raw_bags` reads sweeps straight from a bag, `rosbag_import` writes the generic
  layout).

Import the module you need (`from neld_jax.data.preprocess import select_keyframes`); this package file imports
nothing, so that `import neld_jax.data.poses` stays light.
"""

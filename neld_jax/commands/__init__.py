"""The command-line entry points, one module per command (console scripts in pyproject.toml, and bin/*.py):
neld-train, neld-baseline, neld-evaluate, neld-crispness, neld-import-rosbag, neld-perturb, neld-make-synthetic,
neld-localize.
Each parses its flags, calls the library and prints; bad input is one line on stderr (neld_jax.cli)."""

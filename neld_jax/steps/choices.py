"""The steps' choices that the config offers, in a module that imports nothing: `neld_jax.config` reads them
without loading the steps (Open3D, JAX)."""

START_POSES = ("input", "baseline", "crisper")  # start.poses: where training starts (neld_jax.steps.start)

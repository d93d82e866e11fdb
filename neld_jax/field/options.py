"""The field's choices that the config offers, in a module that imports nothing: `neld_jax.config` reads them
without loading JAX and Flax."""

MATMUL_DTYPES = ("float32", "bfloat16")  # model.matmul_dtype: the hidden matmuls' inputs (density.DensityMLP)
HIERARCHICAL = ("before", "nerf", "none")  # sampling.hierarchical: the fine samples' scheme (model.render_rays)

"""neld-jax: Neural LiDAR Bundle Adjustment (NeLD-BA) in JAX/Flax.

The maths (`lie`, `encoding`, `sampling`, `rendering`, `losses`), the model (`field`, `model`) and the trainer
(`train`, `checkpoint`) are pure, jit-compatible building blocks; `data` reads sequences; `config`, `submaps`,
`baseline`, `judge`, `crispness` and `metrics` are the library; `start`, `refine` and `mapping` are the steps of a
run, which `run.run` chains together; `outputs`, `export`, `evaluate` and `commands` are the edge. docs/design.md
draws the layers.
"""

__version__ = "0.1.0"

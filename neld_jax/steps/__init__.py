"""The steps of a run (neld_jax.run calls them in turn): the input (`inputs`: read, then the front-end where the
scans have no poses), the start (`start`), NeLD-BA on the keyframes (`refine`), the rendered map (`mapping`), every
scan registered to the result (`registration`), and several recordings put in one frame (`session_alignment`).
No wing imports a step. A step takes the config's groups it reads, or a frozen settings dataclass built from them
once at the edge (its from_config, called in neld_jax.run and neld_jax.commands), never the whole config."""

"""Training the field and the poses: the one parameter pytree, its masked optimiser and the jitted step (`train`),
the training rays (`rays`), the plan of cubes (`submaps`), Orbax checkpoints (`checkpoint`) and the run's one
wall clock (`budget`). No I/O library besides Orbax."""

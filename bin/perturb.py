#!/usr/bin/env python
"""neld-perturb, run from a checkout: see neld_jax/commands/perturb.py for its usage."""

from neld_jax.commands.perturb import main

if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""neld-make-synthetic, run from a checkout: see neld_jax/commands/make_synthetic.py for its usage."""

from neld_jax.commands.make_synthetic import main

if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""neld-crispness, run from a checkout: see neld_jax/commands/crispness.py for its usage."""

from neld_jax.commands.crispness import main

if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""neld-evaluate, run from a checkout: see neld_jax/commands/evaluate.py for its usage."""

from neld_jax.commands.evaluate import main

if __name__ == "__main__":
    main()

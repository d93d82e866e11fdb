#!/usr/bin/env python
"""neld-train, run from a checkout: see neld_jax/commands/train.py for its usage."""

from neld_jax.commands.train import main

if __name__ == "__main__":
    main()

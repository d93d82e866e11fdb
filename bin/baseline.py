#!/usr/bin/env python
"""neld-baseline, run from a checkout: see neld_jax/commands/baseline.py for its usage."""

from neld_jax.commands.baseline import main

if __name__ == "__main__":
    main()

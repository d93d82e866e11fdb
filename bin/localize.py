#!/usr/bin/env python
"""neld-localize, run from a checkout: see neld_jax/commands/localize.py for its usage."""

from neld_jax.commands.localize import main

if __name__ == "__main__":
    main()

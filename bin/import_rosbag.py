#!/usr/bin/env python
"""neld-import-rosbag, run from a checkout: see neld_jax/commands/import_rosbag.py for its usage."""

from neld_jax.commands.import_rosbag import main

if __name__ == "__main__":
    main()

"""Recordings joined into one sequence, as the baseline sees them (neld_jax.data.sessions joins them): where each
later one begins, and the relative poses its placing measured between its scans and the first one's.

Each later recording was placed in the first one's frame against the first one's INPUT poses, while the chain moves
those by the drift it corrects. A chain run on through a recording's first scan would place it from the last scan of
the one before by the input's step between them, and so hand the earlier recording's correction on to the later one
(0.7 m between two synthetic visits, beyond the pose graph's loop gates); the chain restarts there instead
(neld_jax.baseline.chain), and the placing's closures join the recordings in the pose graph (neld_jax.baseline.graph).
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Segments:
    """starts: the first scan of each recording after the first, ascending (none: one recording); links:
    ((i, j, transform [4, 4]), ...): scan i of a later recording and scan j of an earlier one seen as one place, the
    transform mapping scan i's points into scan j's frame (Open3D's pose-graph edge, T_j^-1 T_i)."""

    starts: tuple = ()
    links: tuple = ()

    def first_of(self, s: int) -> int:
        """The first scan of scan s's recording."""
        return max([0] + [start for start in self.starts if start <= s])

    def check(self, num_scans: int) -> None:
        """A ValueError naming what does not fit a sequence of num_scans scans."""
        starts = [int(start) for start in self.starts]
        if starts != sorted(set(starts)) or any(not 0 < start < num_scans for start in starts):
            raise ValueError(f"segment starts must ascend within 1..{num_scans - 1}, got {starts}")
        for i, j, transform in self.links:
            if not (0 <= i < num_scans and 0 <= j < num_scans) or np.shape(transform) != (4, 4):
                raise ValueError(
                    f"a link joins scans 0..{num_scans - 1} by a [4, 4] transform, got ({i}, {j}) and "
                    f"shape {np.shape(transform)}"
                )

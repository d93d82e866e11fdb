"""Scans read from disk when they are used, one at a time, in order or by index again later.

A recording of raw sweeps does not fit in memory (an OS0-128 sweep is about 131k points: a 10-minute recording is
several GB as float64), so a loader whose scans are files gives `Sequence.scans` as a `LazyScans`: a read-only
sequence of S arrays [N_i, 3] whose `scans[i]` reads scan i from its file and whose iteration reads them in order,
each dropped by the caller once used. What is derived from a scan (the points moved into another frame, deskewed,
cropped, its per-point times from its azimuths) is a `MappedScans` over it, computed again on each access. Only
the keyframes' points are kept in memory (data.preprocess); the odometry keeps its poses and nothing of the sweeps
(data.odometry), and the registration of every scan reads each again (neld_jax.steps.registration).

The last item read is kept (one scan), so that two views of one scan read together (its points and its per-point
times derived from them) read the file once; a caller must not change an array it gets in place (the next reader
of that scan would get the change). They are not marked read-only: KISS-ICP's bindings refuse read-only arrays.
"""

from __future__ import annotations

import collections.abc
import os
from pathlib import Path
from typing import Callable

import numpy as np


class LazyScans(collections.abc.Sequence):
    """S items (scans [N_i, 3], or per-point times [N_i]) made when indexed; subclasses define `_make(i)`.

    scans[i] (i an int, negative from the end) reads item i; scans[a:b] or scans[[i, j]] is a LazyScans of those;
    iterating reads every item in order. The item last made is kept for the next access of the same index."""

    def __init__(self, count: int):
        self._count = int(count)
        self._last: tuple[int, object] | None = None

    def __len__(self) -> int:
        return self._count

    def __getitem__(self, index):
        if isinstance(index, slice):
            return Subset(self, np.arange(self._count)[index])
        if isinstance(index, (list, tuple, np.ndarray)):
            return Subset(self, np.asarray(index, dtype=np.int64).reshape(-1))
        i = int(index)
        if i < 0:
            i += self._count
        if not 0 <= i < self._count:
            raise IndexError(f"scan {index} of {self._count}")
        if self._last is None or self._last[0] != i:
            self._last = (i, self._make(i))
        return self._last[1]

    def _make(self, i: int):
        raise NotImplementedError

    def map(self, transform: Callable, *others: "LazyScans") -> "MappedScans":
        """The items transform(i, self[i], *(other[i] for other in others)), made on access."""
        return MappedScans(transform, self, *others)


class ScanFiles(LazyScans):
    """The scans of files [S] (.pcd, .ply, .bin, .npy), each read by `read(path)` when used: [N_i, 3] float64,
    without the points that are no measurement (data.scans.read_scan)."""

    def __init__(self, files: list[str | os.PathLike], read: Callable | None = None):
        super().__init__(len(files))
        self.files = [Path(f) for f in files]
        self._read = read

    def _make(self, i: int) -> np.ndarray:
        if self._read is None:
            from neld_jax.data.scans import read_scan

            return read_scan(self.files[i])
        return self._read(self.files[i])


class MappedScans(LazyScans):
    """transform(i, *(source[i] for source in sources)) for each i, made on access (sources of one length)."""

    def __init__(self, transform: Callable, *sources: LazyScans):
        lengths = {len(source) for source in sources}
        if len(lengths) != 1:
            raise ValueError(f"sources of different lengths {sorted(lengths)}")
        super().__init__(lengths.pop())
        self.transform, self.sources = transform, sources

    def _make(self, i: int):
        return self.transform(i, *(source[i] for source in self.sources))


class Subset(LazyScans):
    """The items indices [K] of source, made on access."""

    def __init__(self, source: LazyScans, indices: np.ndarray):
        super().__init__(len(indices))
        self.source, self.indices = source, np.asarray(indices, dtype=np.int64)

    def _make(self, i: int):
        return self.source[int(self.indices[i])]


class HeldScans(LazyScans):
    """Arrays held in memory (a list) seen as a LazyScans, so that views derived from them are made on access."""

    def __init__(self, items: list):
        super().__init__(len(items))
        self.items = items

    def _make(self, i: int):
        return self.items[i]


class Joined(LazyScans):
    """The items of several sources one after another (as one list would hold them), made on access."""

    def __init__(self, sources: list):
        self.sources = [lazy(source) for source in sources]
        self.offsets = np.cumsum([0] + [len(source) for source in self.sources])
        super().__init__(int(self.offsets[-1]))

    def _make(self, i: int):
        part = int(np.searchsorted(self.offsets, i, side="right")) - 1
        return self.sources[part][i - int(self.offsets[part])]


def lazy(items) -> LazyScans:
    """items as a LazyScans: itself when it is one, else a HeldScans of the list."""
    return items if isinstance(items, LazyScans) else HeldScans(list(items))


def is_lazy(items) -> bool:
    """Whether items are read when used (a LazyScans) rather than held in memory (a list)."""
    return isinstance(items, LazyScans)

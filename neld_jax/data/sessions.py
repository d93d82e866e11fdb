"""Several recordings of one place as one sequence: `data.root` names their folders, comma-separated; each is read
as one sequence (its layout's poses or KISS-ICP's, its own keyframes), and `concatenate` joins them, once each is
in the first one's frame, into the sequence a run trains on, remembering which scans are whose (`Sessions`).

The joined stamps are each recording's own, shifted so that they follow one another with SESSION_GAP_S between
them: every step that interpolates by time (the corrections of the scans between keyframes) then never mixes two
recordings. `Sessions.stamps` gives each recording its own stamps back.
"""

from __future__ import annotations

import dataclasses
import logging
import os

import numpy as np

from neld_jax.data.scan_source import Joined, is_lazy
from neld_jax.data.sequence import Sequence

logger = logging.getLogger(__name__)

SESSION_GAP_S = 1.0e4  # between one recording's last stamp and the next one's first, in the joined sequence


def session_roots(root: str) -> list[str]:
    """data.root -> its folders: one, or several separated by commas (blanks around them dropped)."""
    return [part.strip() for part in str(root or "").split(",") if part.strip()]


def session_names(roots: list[str]) -> list[str]:
    """The output folder name of each recording: "<k>_<folder name>" (k from 0, the first recording's frame)."""
    return [f"{k}_{os.path.basename(os.path.normpath(root)) or 'root'}" for k, root in enumerate(roots)]


@dataclasses.dataclass(frozen=True)
class Sessions:
    """Which scans of a joined sequence are whose. names [R]; scan_bounds [R + 1] and keyframe_bounds [R + 1]:
    recording r holds the joined input scans scan_bounds[r]:scan_bounds[r + 1] (and keyframes likewise);
    time_shift_s [R]: what was added to its stamps; to_first [R, 4, 4]: its frame -> the first one's
    (to_first[0] the identity); closures [R]: each recording's places shared with the first, as metrics.json records
    them ([] for the first); closure_transforms [R]: each one's transforms [4, 4] in that order, mapping its keyframe
    into the first recording's (`keyframe_links`)."""

    names: list
    scan_bounds: np.ndarray
    keyframe_bounds: np.ndarray
    time_shift_s: np.ndarray
    to_first: np.ndarray
    closures: list = dataclasses.field(default_factory=list)
    closure_transforms: list = dataclasses.field(default_factory=list)

    @property
    def count(self) -> int:
        return len(self.names)

    def scans_of(self, r: int) -> slice:
        return slice(int(self.scan_bounds[r]), int(self.scan_bounds[r + 1]))

    def keyframes_of(self, r: int) -> slice:
        return slice(int(self.keyframe_bounds[r]), int(self.keyframe_bounds[r + 1]))

    def scan_labels(self) -> np.ndarray:
        """[S] int64: the recording of each joined input scan."""
        return np.repeat(np.arange(self.count), np.diff(self.scan_bounds))

    def keyframe_links(self) -> list[tuple[int, int, np.ndarray]]:
        """The closures as joined keyframes: [(keyframe i of a later recording, keyframe j of the first, transform
        [4, 4] mapping keyframe i's frame into keyframe j's)]."""
        return [
            (
                int(self.keyframe_bounds[r]) + closure["keyframe"],
                closure["first_keyframe"],
                np.asarray(transform, np.float64),
            )
            for r, (closures, transforms) in enumerate(zip(self.closures, self.closure_transforms))
            for closure, transform in zip(closures, transforms)
        ]

    def stamps(self, r: int, joined_stamps: np.ndarray) -> np.ndarray:
        """Recording r's own stamps [S_r] from the joined ones [S]."""
        return np.asarray(joined_stamps, np.float64)[self.scans_of(r)] - self.time_shift_s[r]


def _time_shifts(sequences: list[Sequence]) -> np.ndarray:
    """[R] seconds to add to each sequence's stamps so that each begins SESSION_GAP_S after the one before ends."""
    shifts, end = [], None
    for seq in sequences:
        stamps = seq.timestamps if seq.timestamps is not None else np.arange(seq.num_scans, dtype=np.float64)
        shift = 0.0 if end is None else end + SESSION_GAP_S - float(stamps[0])
        shifts.append(shift)
        end = float(stamps[-1]) + shift
    return np.asarray(shifts, np.float64)


def _joined(parts: list, shifts: np.ndarray, to_first: np.ndarray, names: list[str], index_offsets) -> Sequence:
    """The sequences `parts` as one: poses moved by to_first [R, 4, 4], stamps shifted by shifts [R], files under
    the recording's name, source_index moved by index_offsets [R] (None: none). Ground truth (poses, map) only where
    every recording has it: it is in one frame for all (one alignment of the whole trajectory is measured)."""

    def every(field):
        values = [getattr(seq, field) for seq in parts]
        return None if any(value is None for value in values) else values

    gt_poses, gt_map, times = every("gt_poses"), every("gt_map"), every("point_times")
    stamps = [
        (seq.timestamps if seq.timestamps is not None else np.arange(seq.num_scans, dtype=np.float64)) + shift
        for seq, shift in zip(parts, shifts)
    ]
    files = [
        os.path.join(name, f) if seq.files is not None else f"{name}: scan {i}"
        for seq, name in zip(parts, names)
        for i, f in enumerate(seq.files or [None] * seq.num_scans)
    ]
    index = (
        None
        if index_offsets is None
        else np.concatenate([seq.loaded_index + offset for seq, offset in zip(parts, index_offsets)])
    )
    return Sequence(
        scans=_joined_items([seq.scans for seq in parts]),
        poses=np.concatenate([transform @ seq.poses for seq, transform in zip(parts, to_first)]),
        timestamps=np.concatenate(stamps),
        gt_poses=None if gt_poses is None else np.concatenate(gt_poses),
        gt_map=None if gt_map is None else np.concatenate(gt_map),
        name="+".join(seq.name for seq in parts),
        source=",".join(seq.source for seq in parts),
        files=files,
        source_index=index,
        point_times=None if times is None else _joined_items(times),
        poses_from="kiss_icp" if all(seq.poses_from == "kiss_icp" for seq in parts) else "",
    )


def _joined_items(parts: list) -> list | Joined:
    """The recordings' scans (or point times) one after another: read when used where any recording's are (so a
    long recording is not read into memory by joining it), else one list of the held arrays."""
    if any(is_lazy(items) for items in parts):
        return Joined(parts)
    return [item for items in parts for item in items]


def concatenate(
    loaded: list[Sequence], keyframes: list[Sequence], to_first: np.ndarray, names: list[str]
) -> tuple[Sequence, Sequence, Sessions]:
    """R recordings (each: every input scan `loaded[r]`, its keyframes `keyframes[r]`, poses in its own frame) and
    each one's frame -> the first one's (to_first [R, 4, 4]) -> (every input scan joined, the keyframes joined,
    which are whose)."""
    shifts = _time_shifts(loaded)
    scan_bounds = np.concatenate([[0], np.cumsum([seq.num_scans for seq in loaded])]).astype(np.int64)
    keyframe_bounds = np.concatenate([[0], np.cumsum([seq.num_scans for seq in keyframes])]).astype(np.int64)
    missing = [name for seq, name in zip(loaded, names) if seq.gt_poses is None]
    if missing and len(missing) < len(loaded):
        logger.warning(
            "no ground-truth poses for %s: the recordings are evaluated without ground truth", ", ".join(missing)
        )
    joined_loaded = _joined(loaded, shifts, to_first, names, None)
    joined_keyframes = _joined(keyframes, shifts, to_first, names, scan_bounds[:-1])
    return (
        joined_loaded,
        joined_keyframes,
        Sessions(list(names), scan_bounds, keyframe_bounds, shifts, np.asarray(to_first, np.float64)),
    )

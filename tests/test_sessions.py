"""Several recordings of one place in one run: each later recording placed in the first one's frame (place
recognition, global registration, overlap check), a recording of another place refused, the joined sequence, each
recording's outputs and its ATE under one alignment shared by all."""

import dataclasses
import json
import os

import numpy as np
import pytest
from conftest import make_tiny_config

from neld_jax import baseline, run
from neld_jax.data import sessions as data_sessions
from neld_jax.data.poses import read_tum
from neld_jax.data.preprocess import KeyframeSettings, preprocess
from neld_jax.data.sequence import Sequence
from neld_jax.errors import DataError
from neld_jax.geometry import invert_poses, rotation_angles_deg
from neld_jax.steps import session_alignment, start
from neld_jax.synthetic.generator import make_sequence, write_generic
from neld_jax.writing.session_outputs import shared_alignment_ate

SMALL_VISIT = dict(num_scans=12, num_columns=256, gt_map_points=0)


def _yaw_pose(yaw_deg: float, translation) -> np.ndarray:
    c, s = np.cos(np.deg2rad(yaw_deg)), np.sin(np.deg2rad(yaw_deg))
    pose = np.eye(4)
    pose[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = translation
    return pose


def test_a_later_recording_is_placed_by_the_transform_it_was_moved_by():
    keyframes = preprocess(make_sequence(SMALL_VISIT, session=0))
    later_to_first = _yaw_pose(40.0, (6.0, -4.0, 0.3))
    later_poses = invert_poses(later_to_first) @ keyframes.poses  # the same scans, seen from another frame
    found, closures = session_alignment.align_session(
        (keyframes.scans, keyframes.poses), (keyframes.scans, later_poses), "1_later", "0_first"
    )
    error = invert_poses(later_to_first) @ found
    assert np.linalg.norm(error[:3, 3]) < 0.05
    assert rotation_angles_deg(error[None, :3, :3])[0] < 0.5
    assert closures and all(c.overlap >= session_alignment.MIN_OVERLAP for c in closures)


def test_a_recording_of_another_place_is_refused_naming_it_and_its_best_overlap():
    first = preprocess(make_sequence(SMALL_VISIT, session=0))
    elsewhere = preprocess(make_sequence({**SMALL_VISIT, "seed": 7}, session=1))
    with pytest.raises(DataError, match=r"recording 1_elsewhere matches no place of 0_first \(best overlap "):
        session_alignment.align_session(
            (first.scans, first.poses), (elsewhere.scans, elsewhere.poses), "1_elsewhere", "0_first"
        )


def _sequence(num_scans: int, start_s: float, with_gt: bool = True) -> Sequence:
    poses = np.tile(np.eye(4), (num_scans, 1, 1))
    poses[:, 0, 3] = np.arange(num_scans)
    return Sequence(
        scans=[np.ones((3, 3)) * k for k in range(num_scans)],
        poses=poses,
        timestamps=start_s + np.arange(num_scans, dtype=np.float64),
        gt_poses=poses if with_gt else None,
        files=[f"{k}.pcd" for k in range(num_scans)],
    )


def test_joined_recordings_keep_their_frames_stamps_and_which_scans_are_whose():
    loaded = [_sequence(5, 100.0), _sequence(4, 0.0)]
    every_two_seconds = KeyframeSettings(keyframe_interval_s=2.0, voxel_size=0.0, min_range=0.0)
    keyframes = [preprocess(seq, every_two_seconds) for seq in loaded]
    to_first = np.stack([np.eye(4), _yaw_pose(90.0, (1.0, 2.0, 0.0))])
    joined, joined_keyframes, sessions = data_sessions.concatenate(loaded, keyframes, to_first, ["0_a", "1_b"])
    assert joined.num_scans == 9 and list(sessions.scan_labels()) == [0] * 5 + [1] * 4
    assert np.all(np.diff(joined.timestamps) > 0)  # interpolation by time never mixes two recordings
    assert np.allclose(sessions.stamps(1, joined.timestamps), loaded[1].timestamps)
    assert np.allclose(joined.poses[5:], to_first[1] @ loaded[1].poses)
    # the keyframes index the joined input scans
    assert np.allclose(joined.poses[joined_keyframes.loaded_index], joined_keyframes.poses)
    assert joined.files[5] == os.path.join("1_b", "0.pcd")
    assert data_sessions.session_roots(" /a/x , /b/y,") == ["/a/x", "/b/y"]
    assert data_sessions.session_names(["/a/x", "/b/y/"]) == ["0_x", "1_y"]


def test_the_baseline_sees_where_each_later_recording_begins_and_the_closures_that_placed_it():
    loaded = [_sequence(5, 100.0), _sequence(4, 0.0)]
    every_scan = KeyframeSettings(keyframe_interval_s=2.0, voxel_size=0.0, min_range=0.0)
    keyframes = [preprocess(seq, every_scan) for seq in loaded]
    _, _, sessions = data_sessions.concatenate(loaded, keyframes, np.stack([np.eye(4), np.eye(4)]), ["0_a", "1_b"])
    assert start.segments_of(None) == baseline.Segments()  # one recording: no restart, no link
    assert start.segments_of(sessions).links == ()  # no closures recorded
    place = _yaw_pose(10.0, (0.5, 0.0, 0.0))
    closure = {"keyframe": 1, "first_keyframe": 2, "overlap": 0.8, "map_closures_inliers": 5, "by": "local maps"}
    records = [[], [closure]]
    sessions = dataclasses.replace(sessions, closures=records, closure_transforms=[[], [place]])
    segments = start.segments_of(sessions)
    first_of_second = int(sessions.keyframe_bounds[1])
    assert first_of_second == keyframes[0].num_scans and segments.starts == (first_of_second,)
    ((i, j, transform),) = segments.links
    assert (i, j) == (first_of_second + 1, 2) and np.array_equal(transform, place)


def test_one_shared_alignment_shows_a_misplaced_recording_that_its_own_would_hide():
    gt = np.tile(np.eye(4), (20, 1, 1))
    angle = np.linspace(0, 2 * np.pi, 20, endpoint=False)
    gt[:, 0, 3], gt[:, 1, 3] = 10 * np.cos(angle), 10 * np.sin(angle)
    labels = np.repeat([0, 1], 10)
    moved = _yaw_pose(30.0, (5.0, 1.0, 0.0)) @ gt  # one frame for both: no error under one alignment
    assert all(a["translation_rmse_m"] < 1e-9 for a in shared_alignment_ate(moved, gt, labels))
    misplaced = moved.copy()
    misplaced[10:, 0, 3] += 1.0  # the second recording 1 m off: its own alignment would hide it
    first, second = shared_alignment_ate(misplaced, gt, labels)
    assert second["translation_rmse_m"] > 0.3 and first["alignment"] == second["alignment"]


def test_a_run_over_two_recordings_writes_each_ones_poses_report_and_shared_ate(tmp_path, monkeypatch):
    tiny = make_tiny_config().data.synthetic.to_dict()
    visits = [make_sequence({**tiny, "num_scans": n}, session=k) for k, n in ((0, 4), (1, 3))]
    for visit, name in zip(visits, ("a", "b")):
        write_generic(visit, tmp_path / name)
    # the recordings' true relative frame (each starts at its first scan): tiny scans are too sparse to place
    truth = invert_poses(visits[0].gt_poses[0]) @ visits[1].gt_poses[0]
    monkeypatch.setattr(session_alignment, "align_session", lambda *args: (truth, []))
    config = make_tiny_config(str(tmp_path / "out"), steps=4)
    config.data.format, config.data.root = "generic", f"{tmp_path / 'a'},{tmp_path / 'b'}"
    config.sampling.coarse_stages, config.sampling.fine_stages = (8,), (4,)
    config.mapping.enabled = False
    run.run(config, progress=False)
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    recordings = metrics["sessions"]["recordings"]
    assert [r["name"] for r in recordings] == ["0_a", "1_b"] and [r["scans"] for r in recordings] == [4, 3]
    for r, visit in zip(recordings, visits):
        folder = tmp_path / "out" / "sessions" / r["name"]
        stamps, poses = read_tum(folder / "poses_optimized.txt")
        assert np.allclose(stamps, visit.timestamps) and len(poses) == visit.num_scans
        assert (folder / "poses_optimized.kitti").is_file()
        assert len((folder / "scans_report.csv").read_text().splitlines()) == visit.num_scans + 1
        shared = r["ate_shared_alignment"]["optimized"]
        assert shared["alignment"] == recordings[0]["ate_shared_alignment"]["optimized"]["alignment"]
        assert shared["translation_rmse_m"] < 0.5  # placed by the true transform: no recording misplaced
        assert r["crispness"]["in_merged_keyframe_entropy"] is not None

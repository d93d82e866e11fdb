"""The run's Rerun recording (writing.viewer), read back through Rerun's own reader: the entities, their counts and
values (the refined poses equal poses_optimized.txt), the training curves; no display and no network."""

import csv
import json

import numpy as np
import pytest
from conftest import make_tiny_config
from rerun.chunk import RrdReader

from neld_jax import run
from neld_jax.data.poses import read_tum
from neld_jax.writing import viewer


def read_recording(path) -> dict:
    """{entity path: {column: list of values, one per row, over every chunk}} of a .rrd file."""
    entities: dict = {}
    for chunk in RrdReader(str(path)).stream().collect().stream():
        batch = chunk.to_record_batch().to_pydict()
        columns = entities.setdefault(chunk.entity_path, {})
        for name, values in batch.items():
            columns.setdefault(name, []).extend(values)
    return entities


@pytest.fixture(scope="module")
def recorded_run(free_gauge_run):
    return free_gauge_run, read_recording(free_gauge_run / viewer.RECORDING)


def test_the_recording_holds_the_runs_entities(recorded_run):
    out, entities = recorded_run
    expected = {
        "/world/trajectory/input",
        "/world/trajectory/refined",
        "/world/trajectory/gt",
        "/world/trajectory/training",
        "/world/scans/input",
        "/world/scans/refined",
        "/world/scans/report",
        "/world/map/raw_input",
        "/world/map/raw_refined",
        "/world/map/rendered",
        "/world/map/gt",
        "/train/loss",
        "/train/range_err_m",
        "/train/frequency",
        "/train/pose_change_cm",
        "/train/lr/field",
        "/train/lr/pose_trans",
        "/train/lr/pose_rot",
    }
    assert expected <= set(entities), sorted(expected - set(entities))
    # no baseline ran (the start is the input): no baseline trajectory
    assert "/world/trajectory/baseline" not in entities


def test_the_refined_poses_in_the_recording_are_the_written_ones(recorded_run):
    out, entities = recorded_run
    _, T_optimized = read_tum(out / "poses_optimized.txt")
    _, T_initial = read_tum(out / "poses_initial.txt")
    (refined,) = entities["/world/trajectory/refined"]["LineStrips3D:strips"]
    np.testing.assert_allclose(np.array(refined[0]), T_optimized[:, :3, 3], atol=1e-5)
    (initial,) = entities["/world/trajectory/input"]["LineStrips3D:strips"]
    np.testing.assert_allclose(np.array(initial[0]), T_initial[:, :3, 3], atol=1e-5)
    # one arrow per keyframe, along its x axis
    (origins,) = entities["/world/scans/refined"]["Arrows3D:origins"]
    (vectors,) = entities["/world/scans/refined"]["Arrows3D:vectors"]
    assert len(origins) == len(T_optimized) == 4
    directions = np.array(vectors) / np.linalg.norm(vectors, axis=1, keepdims=True)
    np.testing.assert_allclose(directions, T_optimized[:, :3, 0], atol=1e-5)


def test_each_scan_carries_its_report(recorded_run):
    out, entities = recorded_run
    with open(out / "scans_report.csv") as f:
        rows = list(csv.DictReader(f))
    report = entities["/world/scans/report"]
    (positions,) = report["Points3D:positions"]
    (labels,) = report["Points3D:labels"]
    assert len(positions) == len(labels) == len(rows) == 4
    assert labels[0].startswith("scan 0")
    (correction,) = report["correction_cm"]
    np.testing.assert_allclose(correction, [float(r["correction_cm"]) for r in rows], atol=1e-5)
    (residual,) = report["residual_cm"]
    np.testing.assert_allclose(residual, [100 * float(r["median_residual_m"]) for r in rows], atol=1e-4)
    # ground truth exists (synthetic): each scan's error against it
    (error_cm,) = report["error_cm"]
    ate = json.loads((out / "metrics.json").read_text())["evaluation"]["methods"]["optimized"]["ate"]
    assert np.sqrt(np.mean(np.square(error_cm))) / 100 == pytest.approx(ate["translation_rmse_m"], rel=1e-4)
    (error_deg,) = report["error_deg"]
    assert np.sqrt(np.mean(np.square(error_deg))) == pytest.approx(ate["rotation_rmse_deg"], rel=1e-4)


def test_training_is_logged_over_steps(recorded_run):
    out, entities = recorded_run
    history = json.loads((out / "history.json").read_text())
    loss = entities["/train/loss"]
    assert loss["step"] == [h["step"] for h in history] == list(range(1, 13))
    np.testing.assert_allclose(np.concatenate(loss["Scalars:scalars"]), [h["loss"] for h in history], rtol=1e-6)
    field_lr = np.concatenate(entities["/train/lr/field"]["Scalars:scalars"])
    assert field_lr[0] == pytest.approx(1e-3) and field_lr[-1] < field_lr[0]  # the tiny config's decay
    # the keyframes' poses at every logged step: the last is the refined trajectory's keyframes
    training = entities["/world/trajectory/training"]
    assert training["step"] == list(range(1, 13))
    _, T_optimized = read_tum(out / "poses_optimized.txt")
    np.testing.assert_allclose(np.array(training["LineStrips3D:strips"][-1][0]), T_optimized[:, :3, 3], atol=1e-5)


def test_maps_are_thinned_and_coloured_by_height():
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 10, size=(5000, 3))
    thinned = viewer.thin_for_viewing(points, max_points=1000)
    assert len(thinned) <= 1000 and len(viewer.thin_for_viewing(points, max_points=10_000)) == 5000
    # the voxel is chosen by counting: the count is exactly what Open3D's downsample returns at that size
    from neld_jax.data.preprocess import voxel_downsample

    for voxel in (0.05, 0.7, 1.3, 4.0):
        assert viewer.occupied_voxels(points, voxel) == len(voxel_downsample(points, voxel))
    chosen = voxel_downsample(points, 0.02 * 2**6)  # 2 cm doubled to 1.28 m, the first size with <= 1000
    np.testing.assert_allclose(np.sort(thinned, axis=0), np.sort(chosen, axis=0))
    colours = viewer.height_colours(np.array([0.0, 5.0, 10.0]))
    assert colours.dtype == np.uint8 and colours.shape == (3, 3) and not np.array_equal(colours[0], colours[2])


def test_no_recording_when_switched_off(tmp_path):
    viz = make_tiny_config().viz
    viz.record = False
    off = viewer.RunViewer.open(str(tmp_path), viz)
    assert not off.enabled and off.training_hook() is None
    off.log_input(None, None)  # a disabled viewer takes every call and touches nothing
    off.log_verdict([], None, None)
    off.close()
    assert list(tmp_path.iterdir()) == []


def test_live_view_serves_on_a_local_port_and_still_records(tmp_path, monkeypatch):
    import socket

    with socket.socket() as s:  # a free port: two test workers may run at once
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(viewer, "LIVE_PORT", port)
    viz = make_tiny_config().viz
    viz.live = True
    live = viewer.RunViewer.open(str(tmp_path), viz)
    assert live.live_url == f"rerun+http://127.0.0.1:{port}/proxy"
    with socket.create_connection(("127.0.0.1", port), timeout=5):  # the server listens
        pass
    live.training_hook()({"step": 1, "loss": 0.5}, np.tile(np.eye(4), (3, 1, 1)))
    live.close()
    del live
    entities = read_recording(tmp_path / viewer.RECORDING)
    assert entities["/train/loss"]["step"] == [1] and len(entities["/world/trajectory/training"]["step"]) == 1


def test_a_run_that_fails_midway_leaves_a_closed_recording_that_says_why(tmp_path, monkeypatch):
    def broken_training(*args, **kwargs):
        raise RuntimeError("training broke on purpose")

    monkeypatch.setattr(run.refine, "refine_keyframes", broken_training)
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="training broke on purpose"):
        run.run(make_tiny_config(str(out), steps=4), progress=False)
    entities = read_recording(out / viewer.RECORDING)  # Rerun's reader loads it whole
    # what the steps before the failure made is there, and the failure with its traceback
    assert {"/world/trajectory/input", "/world/map/raw_input"} <= set(entities)
    (text,) = entities["/" + viewer.FAILURE_ENTITY]["TextLog:text"]
    (level,) = entities["/" + viewer.FAILURE_ENTITY]["TextLog:level"]
    assert text[0].startswith("the run failed: RuntimeError: training broke on purpose")
    assert "broken_training" in text[0] and level == ["ERROR"]

"""A run as a Rerun recording (run.rrd in the output folder), to look at in Rerun's viewer: the trajectories, the
raw maps before and after, the rendered map, each scan's correction, residual and crispness, training over steps,
and the ground truth with each scan's error where it exists (docs/viewer.md).

The run's steps (neld_jax.run) hand what they made to a `RunViewer` as they go; nothing here runs inside jitted
code, and the maths and the trainer do not import rerun (the trainer's loop calls a plain hook). With viz.live the
same entities also go to a gRPC server on a local port that a viewer connects to while the run trains.

Entities (world frame, z up; timeline "step" for training, everything else static):
  world/trajectory/{input,baseline,refined,gt}  LineStrips3D: every input scan's position (gt aligned, SE(3))
  world/scans/{input,baseline,refined}          Arrows3D: one per keyframe, from its position along its x axis
  world/scans/report                            Points3D: every input scan at its refined position, labelled, with
                                                 correction_cm / correction_deg / residual_cm / entropy_before /
                                                 entropy_after / flag (and error_cm / error_deg against ground
                                                 truth) per scan; flagged scans red and larger
  world/map/{raw_input,raw_refined,rendered,gt} Points3D coloured by height, voxel-thinned to MAX_MAP_POINTS
  world/trajectory/training                     LineStrips3D of the keyframes' poses at each logged step
  train/{loss,range_err_m,frequency,pose_change_cm,pose_change_deg,lr/field,lr/pose_trans,lr/pose_rot}  Scalars
  run/failure                                   TextLog (level ERROR): the error that stopped a run, with its
                                                 traceback; the recording is closed and complete all the same
"""

from __future__ import annotations

import functools
import logging
import os
import time
import traceback

import ml_collections
import numpy as np

from neld_jax.geometry import register_scans
from neld_jax.judging.metrics import ate_errors
from neld_jax.trajectory import propagate_corrections

logger = logging.getLogger(__name__)

RECORDING = "run.rrd"
FAILURE_ENTITY = "run/failure"
APPLICATION_ID = "neld-jax"
LIVE_PORT = 9876  # viz.live serves here (Rerun's default port; `rerun rerun+http://127.0.0.1:9876/proxy`)
MAX_MAP_POINTS = 400_000  # a map the viewer opens in a few seconds
MARKER_LENGTH_FRACTION = 0.01  # a scan's arrow, as a fraction of the trajectory's extent
FLAG_COLOUR = (230, 40, 40)
SCAN_COLOUR = (200, 200, 200)
TRAJECTORY_COLOURS = {
    "input": (150, 150, 150),
    "baseline": (60, 130, 230),
    "refined": (40, 200, 90),
    "gt": (240, 180, 20),
    "training": (200, 90, 220),
}
SESSION_COLOURS = ((40, 200, 90), (230, 120, 30), (60, 130, 230), (200, 90, 220), (240, 180, 20), (30, 190, 190))
SCALARS = {
    "loss": "loss",
    "range_err_m": "range_err_m",
    "alpha": "frequency",
    "field_lr": "lr/field",
    "pose_lr_trans": "lr/pose_trans",
    "pose_lr_rot": "lr/pose_rot",
}


def _timed(method):
    """Counts the seconds a viewer call takes toward the run's total (logged at close)."""

    @functools.wraps(method)
    def timed(self, *args, **kwargs):
        if not self.enabled:
            return None
        started = time.perf_counter()
        try:
            return method(self, *args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - started

    return timed


class RunViewer:
    """Logs a run's steps to OUT_DIR/run.rrd (and to a local gRPC server with viz.live). A disabled viewer
    (viz.record and viz.live off) takes every call and does nothing, so the run calls it unconditionally."""

    def __init__(self, stream, live_url: str | None = None, path: str | None = None):
        self._stream = stream
        self._path = path
        self.live_url = live_url
        self._marker_m = 0.1
        self._logged_steps: set[int] = set()
        self.seconds = 0.0  # spent logging

    @classmethod
    def open(cls, out_dir: str, viz: ml_collections.ConfigDict) -> "RunViewer":
        if not (viz.record or viz.live):
            return cls(None)
        import rerun as rr  # an effect at the edge: only a run that records imports it

        stream = rr.RecordingStream(APPLICATION_ID)  # a recording id of its own: two runs open side by side
        sinks, url, path = [], None, None
        if viz.record:
            path = os.path.join(out_dir, RECORDING)
            sinks.append(rr.FileSink(path))
        if viz.live:
            sinks.append(rr.GrpcServerSink("127.0.0.1", LIVE_PORT))
            url = f"rerun+http://127.0.0.1:{LIVE_PORT}/proxy"
            logger.info(
                "live view: `rerun %s` (Rerun's viewer, `pip install rerun-sdk`) shows the run as it trains", url
            )
        stream.set_sinks(*sinks, default_blueprint=layout())
        stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        return cls(stream, url, path)

    @property
    def enabled(self) -> bool:
        return self._stream is not None

    def __enter__(self) -> "RunViewer":
        return self

    def __exit__(self, kind, error, trace) -> bool:
        """Closes the recording however the run ends; a run that failed (or was interrupted) logs why first."""
        try:
            if error is not None:
                self.log_failure(error)
        except Exception as logging_error:  # the run's own error is the one to report
            logger.warning("run.rrd: the failure could not be logged (%s)", logging_error)
        finally:
            self.close()
        return False  # the error goes on

    # ------------------------------------------------------------------------------------------ the steps

    @_timed
    def log_input(self, loaded, keyframes) -> None:
        """Step 1: the input trajectory (every input scan), the keyframes' markers, the raw map from the input,
        and the ground-truth map where there is one."""
        extent = np.ptp(loaded.poses[:, :3, 3], axis=0).max() if loaded.num_scans > 1 else 1.0
        self._marker_m = max(float(extent) * MARKER_LENGTH_FRACTION, 0.05)
        self._trajectory("input", loaded.poses, keyframes.poses)
        self._map("raw_input", register_scans(keyframes.scans, keyframes.poses))
        if keyframes.gt_map is not None:
            self._map("gt", keyframes.gt_map)

    @_timed
    def log_start(self, loaded, keyframes, begin) -> None:
        """Step 2: the classical baseline's trajectory, where it ran."""
        if begin.baseline_poses is None:
            return
        all_scans = propagate_corrections(loaded.poses, keyframes.loaded_index, begin.baseline_poses, loaded.timestamps)
        self._trajectory("baseline", all_scans, begin.baseline_poses)

    def training_hook(self):
        """Step 3: on_log(entry, poses [K, 4, 4]) for neld_jax.steps.refine: the training curves and the keyframes'
        poses at each logged step (None when disabled, so that training runs without a hook)."""
        return self._timed_training_entry if self.enabled else None

    @_timed
    def log_rendered(self, render) -> None:
        """Step 4: the rendered map (the points at argmax h/delta)."""
        if render is not None and len(render.points):
            self._map("rendered", render.points)

    @_timed
    def log_outputs(self, keyframes, refined, T_all: np.ndarray, recordings=None) -> None:
        """Step 5: the refined trajectory (every input scan, as poses_optimized.txt), its markers and raw map, and
        the training curves a resumed run's earlier part logged before this process; several recordings
        (recordings: neld_jax.data.sessions.Sessions): each one's trajectory and raw map in its own colour."""
        for entry in refined.result.history:
            if int(entry["step"]) not in self._logged_steps:
                self._log_training_entry(entry, None)
        self._trajectory("refined", T_all, refined.poses)
        self._map("raw_refined", register_scans(keyframes.scans, refined.poses))
        if recordings is not None:
            self._recordings(recordings, keyframes, refined.poses, T_all)

    def _recordings(self, recordings, keyframes, keyframe_poses: np.ndarray, T_all: np.ndarray) -> None:
        """world/sessions/<name>/trajectory and .../map: each recording's refined trajectory (T_all [S, 4, 4], every
        joined input scan) and its keyframes' raw map (keyframe_poses [K, 4, 4]) in SESSION_COLOURS."""
        import rerun as rr

        for r, name in enumerate(recordings.names):
            colour = SESSION_COLOURS[r % len(SESSION_COLOURS)]
            part = recordings.keyframes_of(r)
            points = thin_for_viewing(
                register_scans(keyframes.scans[part], keyframe_poses[part]), MAX_MAP_POINTS // recordings.count
            )
            self._stream.log(
                f"world/sessions/{name}/trajectory",
                rr.LineStrips3D([T_all[recordings.scans_of(r), :3, 3]], colors=[colour]),
                static=True,
            )
            self._stream.log(
                f"world/sessions/{name}/map", rr.Points3D(points, colors=[colour], radii=0.02), static=True
            )

    @_timed
    def log_verdict(self, rows: list[dict], loaded, T_all: np.ndarray) -> None:
        """Step 6: every scan at its refined position with its row of the per-scan report (judging.report, as in
        scans_report.csv) attached, the flagged scans highlighted; the ground truth (aligned to the refined
        trajectory) and each scan's error against it where it exists."""
        import rerun as rr

        values = {
            name: np.array([_number(row[name]) for row in rows])
            for name in ("correction_cm", "correction_deg", "entropy_before", "entropy_after")
        }
        values["residual_cm"] = 100.0 * np.array([_number(row["median_residual_m"]) for row in rows])
        flags = [row["flag"] for row in rows]
        has_gt = (
            np.zeros(len(T_all), bool) if loaded.gt_poses is None else np.isfinite(loaded.gt_poses).all(axis=(1, 2))
        )
        if has_gt.sum() >= 3:  # the scans with a ground-truth pose, aligned as the ATE aligns them
            errors_m, errors_deg, alignment, _ = ate_errors(T_all[has_gt], loaded.gt_poses[has_gt])
            values["error_cm"], values["error_deg"] = np.full(len(T_all), np.nan), np.full(len(T_all), np.nan)
            values["error_cm"][has_gt], values["error_deg"][has_gt] = 100.0 * errors_m, errors_deg
            self._trajectory("gt", np.linalg.inv(alignment) @ loaded.gt_poses[has_gt], None)
        flagged = np.array([bool(flag) for flag in flags])
        labels = [f"scan {row['scan']}" + (f" ({row['flag']})" if row["flag"] else "") for row in rows]
        self._stream.log(
            "world/scans/report",
            rr.Points3D(
                T_all[:, :3, 3],
                labels=labels,
                colors=np.where(flagged[:, None], FLAG_COLOUR, SCAN_COLOUR).astype(np.uint8),
                radii=np.where(flagged, 2.0, 0.6) * self._marker_m / 4,
            ),
            rr.AnyValues(flag=flags, **values),
            static=True,
        )

    @_timed
    def log_failure(self, error: BaseException) -> None:
        """What stopped the run: the error's line and its traceback, as an error-level text log (FAILURE_ENTITY)."""
        import rerun as rr

        what = "interrupted" if isinstance(error, KeyboardInterrupt) else "failed"
        text = f"the run {what}: {type(error).__name__}: {error}\n" + "".join(
            traceback.format_exception(type(error), error, error.__traceback__)
        )
        self._stream.log(FAILURE_ENTITY, rr.TextLog(text, level=rr.TextLogLevel.ERROR), static=True)

    def close(self) -> None:
        if not self.enabled:
            return
        started = time.perf_counter()
        self._stream.flush()
        if self.live_url is None:
            self._stream.disconnect()
        self.seconds += time.perf_counter() - started
        if self._path is not None:
            logger.info(
                "%s: %.1f MB, %.1f s of logging; open it with `rerun %s`",
                RECORDING,
                os.path.getsize(self._path) / 1e6,
                self.seconds,
                self._path,
            )

    # ------------------------------------------------------------------------------------------ entities

    @_timed
    def _timed_training_entry(self, entry: dict, poses: np.ndarray) -> None:
        self._log_training_entry(entry, poses)

    def _log_training_entry(self, entry: dict, poses: np.ndarray | None) -> None:
        import rerun as rr

        step = int(entry["step"])
        self._logged_steps.add(step)
        self._stream.set_time("step", sequence=step)
        for key, path in SCALARS.items():
            if key in entry:
                self._stream.log(f"train/{path}", rr.Scalars(float(entry[key])))
        if "pose_trans_mean_m" in entry:
            self._stream.log("train/pose_change_cm", rr.Scalars(100.0 * float(entry["pose_trans_mean_m"])))
            self._stream.log("train/pose_change_deg", rr.Scalars(float(entry["pose_rot_mean_deg"])))
        if poses is not None:
            self._stream.log(
                "world/trajectory/training", rr.LineStrips3D([poses[:, :3, 3]], colors=[TRAJECTORY_COLOURS["training"]])
            )
        self._stream.reset_time()

    def _trajectory(self, name: str, poses_all: np.ndarray, poses_keyframes: np.ndarray | None) -> None:
        """A line through every scan's position; an arrow along each keyframe's x axis (its heading)."""
        import rerun as rr

        colour = TRAJECTORY_COLOURS[name]
        self._stream.log(
            f"world/trajectory/{name}", rr.LineStrips3D([poses_all[:, :3, 3]], colors=[colour]), static=True
        )
        if poses_keyframes is not None:
            self._stream.log(
                f"world/scans/{name}",
                rr.Arrows3D(
                    origins=poses_keyframes[:, :3, 3],
                    vectors=self._marker_m * poses_keyframes[:, :3, 0],
                    colors=[colour],
                ),
                static=True,
            )

    def _map(self, name: str, points: np.ndarray) -> None:
        import rerun as rr

        points = thin_for_viewing(np.asarray(points, np.float64))
        self._stream.log(
            f"world/map/{name}", rr.Points3D(points, colors=height_colours(points[:, 2]), radii=0.02), static=True
        )


def layout():
    """The viewer's layout: the maps and trajectories after, before and rendered as tabs of one 3-D view (flip
    between them to see a doubled wall come out single), the training curves beside them."""
    import rerun.blueprint as rrb

    trajectories = [
        "world/trajectory/input",
        "world/trajectory/baseline",
        "world/trajectory/refined",
        "world/trajectory/gt",
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(
                rrb.Spatial3DView(
                    name="after: refined poses",
                    origin="world",
                    contents=[
                        "world/map/raw_refined",
                        "world/scans/refined",
                        "world/scans/report",
                        "world/trajectory/training",
                        *trajectories,
                    ],
                ),
                rrb.Spatial3DView(
                    name="before: input poses",
                    origin="world",
                    contents=["world/map/raw_input", "world/scans/input", *trajectories],
                ),
                rrb.Spatial3DView(
                    name="rendered map",
                    origin="world",
                    contents=["world/map/rendered", "world/map/gt", "world/trajectory/refined"],
                ),
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(name="loss and range error [m]", contents=["train/loss", "train/range_err_m"]),
                rrb.TimeSeriesView(
                    name="pose change (mean)", contents=["train/pose_change_cm", "train/pose_change_deg"]
                ),
                rrb.TimeSeriesView(name="coarse-to-fine frequency", contents=["train/frequency"]),
                rrb.TimeSeriesView(name="learning rates", contents=["train/lr/**"]),
                rrb.TextLogView(name="failure", origin="run"),
            ),
            column_shares=[3, 1],
        ),
        collapse_panels=True,
    )


def thin_for_viewing(points: np.ndarray, max_points: int = MAX_MAP_POINTS) -> np.ndarray:
    """points [N, 3] -> at most max_points: the centroids of the occupied voxels, the voxel doubled from 2 cm
    until they fit. The voxel is found by counting occupied voxels (a sort), and the points are downsampled once:
    a real recording's sparse raw map (2.9 M points) needs 64 cm, and a downsample at each size took 14 s."""
    from neld_jax.data.preprocess import voxel_downsample

    if len(points) <= max_points:
        return points
    voxel = 0.02
    while occupied_voxels(points, voxel) > max_points:
        voxel *= 2.0
    return voxel_downsample(points, voxel)


def occupied_voxels(points: np.ndarray, voxel: float) -> int:
    """How many voxels of size `voxel` points [N, 3] occupy, on the grid Open3D's voxel_down_sample uses (cells
    from the points' minimum less half a voxel): the number of points that downsample returns."""
    keys = np.floor((points - (points.min(axis=0) - 0.5 * voxel)) / voxel).astype(np.int64)
    span = keys.max(axis=0) + 1
    packed = np.sort(keys[:, 0] + span[0] * (keys[:, 1] + span[1] * keys[:, 2]))
    return int(1 + np.count_nonzero(np.diff(packed)))


def height_colours(z: np.ndarray) -> np.ndarray:
    """[N] heights -> [N, 3] uint8 colours (matplotlib's turbo over the 2nd-98th percentile)."""
    from matplotlib import colormaps

    if len(z) == 0:
        return np.zeros((0, 3), np.uint8)
    low, high = np.percentile(z, [2, 98])
    unit = np.clip((z - low) / max(high - low, 1e-9), 0.0, 1.0)
    return (255 * colormaps["turbo"](unit)[:, :3]).astype(np.uint8)


def _number(value: float | None) -> float:
    """A report value, NaN where the report has none (a scan that is not a keyframe)."""
    return float("nan") if value is None else float(value)

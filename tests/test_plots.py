"""The evaluation figures are written as non-empty PNG files; the top view's close-up goes where the maps differ."""

import numpy as np

from neld_jax.writing import plots

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _is_png(path):
    data = path.read_bytes()
    return data.startswith(PNG_SIGNATURE) and len(data) > 2000


def test_plots_write_pngs(tmp_path):
    rng = np.random.default_rng(0)
    gt = np.tile(np.eye(4), (10, 1, 1))
    gt[:, 0, 3] = np.arange(10.0)
    noisy = gt.copy()
    noisy[:, :3, 3] += rng.normal(0, 0.2, (10, 3))

    path = plots.plot_trajectories(tmp_path / "trajectory.png", {"initial": noisy, "optimized": gt}, gt=gt)
    assert path == tmp_path / "trajectory.png" and _is_png(path)
    assert _is_png(plots.plot_trajectories(tmp_path / "no_gt.png", {"initial": noisy}))

    errors = {"initial": np.abs(rng.normal(0, 0.2, 10)), "optimized": np.abs(rng.normal(0, 0.02, 10))}
    assert _is_png(plots.plot_pose_errors(tmp_path / "sub" / "pose_error.png", errors))

    distances = {"raw": np.abs(rng.normal(0, 0.3, 1000)), "empty": np.zeros(0)}
    assert _is_png(plots.plot_error_histogram(tmp_path / "error_histogram.png", distances, threshold=0.2))


def _walls(rng, xs, length, per_wall=4000):
    """Points [len(xs) * per_wall, 3] on vertical walls x = const, y in [0, length], z in [0, 3]."""
    return np.concatenate(
        [
            np.column_stack([np.full(per_wall, x), rng.uniform(0, length, per_wall), rng.uniform(0, 3, per_wall)])
            for x in xs
        ]
    )


def test_map_topdown_close_up_goes_where_the_maps_differ(tmp_path):
    rng = np.random.default_rng(0)
    sharp = _walls(rng, [5.0, 15.0, 25.0, 35.0, 45.0], 20.0)
    blurred = sharp.copy()
    moved = (sharp[:, 0] == 25.0) & (sharp[:, 1] > 10.0)  # one stretch of one wall, as a misregistered scan
    blurred[moved, 0] += rng.normal(0.0, 0.3, moved.sum())
    lo, hi = np.array([0.0, 0.0]), np.array([50.0, 20.0])
    x, y = plots.detail_window([sharp[:, :2], blurred[:, :2]], lo, hi, side=8.0)
    assert x <= 25.0 <= x + 8.0 and y + 8.0 > 10.0  # the window holds the blurred stretch
    assert lo[0] <= x and x + 8.0 <= hi[0] + 8.0 / 64 and lo[1] <= y and y + 8.0 <= hi[1] + 8.0 / 64
    # Wide maps are stacked, others side by side; both write a PNG with the close-ups.
    assert _is_png(plots.plot_map_topdown(tmp_path / "wide.png", {"before": blurred, "after": sharp}))
    tall = sharp[:, [1, 0, 2]]
    assert _is_png(plots.plot_map_topdown(tmp_path / "tall.png", {"before": tall, "after": tall}))
    assert _is_png(plots.plot_map_topdown(tmp_path / "empty.png", {"before": np.zeros((0, 3))}))

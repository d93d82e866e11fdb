"""The evaluation figures are written as non-empty PNG files."""

import numpy as np

from neld_jax import plots

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

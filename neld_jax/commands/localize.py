"""neld-localize (bin/localize.py): pose scans (another recording of a mapped place, or the same scans) in a finished
run's map.

    neld-localize --run=RUN_DIR --config=configs/generic.py:cpu --config.data.root=SCANS --config.output_dir=OUT

Reads the run's map (RUN_DIR/map_raw.ply: its keyframes under the refined poses, in the run's world frame) and the
scans as --config reads them, with their own initial poses (the layout's, or KISS-ICP's where it has none:
data.initial_poses). The first scan is registered to the map from its own pose, or where that fails (another
recording's frame) by global registration (FPFH + RANSAC, then ICP); each next scan by point-to-plane ICP from its
own pose carried by the last registered scan's correction (neld_jax.steps.registration.localize). Writes
OUT/poses_localized.txt (TUM, the run's world frame) with poses_localized.kitti beside it, and OUT/scans_report.csv
(each scan's residual on the map, its fitness, and why a scan was not registered: it then keeps its guess).
"""

import os

from absl import flags

from neld_jax.cli import main_with_config

RUN = flags.DEFINE_string("run", None, "A finished run's output folder (its map_raw.ply is the map).")


def localize_scans(config, run_dir: str, progress: bool = True) -> dict:
    """Pose the scans config.data names in run_dir's map; write OUT's files. Returns a summary (counts, paths)."""
    import numpy as np

    from neld_jax.data.scans import read_scan
    from neld_jax.errors import ConfigError
    from neld_jax.judging import report
    from neld_jax.steps import registration
    from neld_jax.steps.inputs import load_sequence
    from neld_jax.writing.export import write_poses

    map_path = os.path.join(run_dir or "", "map_raw.ply")
    if not run_dir or not os.path.isfile(map_path):
        raise ConfigError(f"--run: {map_path} not found (give a finished run's output folder)")
    settings = registration.RegistrationSettings.from_groups(config.data, config.baseline)
    target = registration.cloud_with_normals(read_scan(map_path), settings)
    scans = load_sequence(config.data)
    registered, how = registration.localize(scans.scans, scans.poses, target, settings, progress, scans.scan_label)
    out_dir = os.path.abspath(config.output_dir)
    tum, _ = write_poses(out_dir, "poses_localized", scans.timestamps, registered.poses)
    rows = report.localization_rows(registered, scans.files, scans.timestamps)
    report.write_csv(os.path.join(out_dir, "scans_report.csv"), rows, report.LOCALIZATION_COLUMNS)
    return {
        "scans": scans.num_scans,
        "registered": int(registered.registered.sum()),
        "first_scan": how,
        "median_residual_m": float(np.nanmedian(registered.residual_m)),
        "poses": str(tum),
    }


def job(config) -> None:
    summary = localize_scans(config, RUN.value)
    print(
        f"{summary['registered']} of {summary['scans']} scans registered to the map (the first by "
        f"{'global registration' if summary['first_scan'] == 'global' else 'ICP from its own pose'}; median "
        f"residual {100 * summary['median_residual_m']:.1f} cm): {summary['poses']}"
    )


def main() -> None:
    main_with_config(job, __doc__)


if __name__ == "__main__":
    main()

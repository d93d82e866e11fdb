"""The run's input, in two named steps: read the scans (neld_jax.data, files only; the synthetic format is made by
neld_jax.synthetic), then, where they come without poses, the front-end (neld_jax.frontend) makes them. Then the
keyframes the field trains on (neld_jax.data.preprocess)."""

from __future__ import annotations

from neld_jax.data import formats
from neld_jax.data.preprocess import KeyframeSettings, preprocess
from neld_jax.data.sequence import Sequence
from neld_jax.frontend.scan_poses import with_scan_poses
from neld_jax.training.stage_plan import front_end_forecast

SYNTHETIC = "synthetic"  # data.format of a generated sequence (neld_jax.synthetic.generator)
FORMATS = (*formats.FORMATS, SYNTHETIC)  # every data.format a run accepts


def load_sequence(data_cfg, progress: bool = True, budget_s: float = 0.0) -> Sequence:
    """The sequence data_cfg (config.data) names, posed: read (or generated), then the front-end's poses where it
    has none (its time forecast first, and a recording too long for budget_s, the run's seconds, told before it
    starts: stage_plan.front_end_forecast). A folder without ground truth is reported with what was looked for
    (formats.report_missing_ground_truth)."""
    if str(data_cfg.format).lower() == SYNTHETIC:
        from neld_jax.synthetic import generator  # here: Open3D's ray casting is only needed to make scans

        seq = generator.load(data_cfg)
        if seq.poses is None or formats.wants_odometry(data_cfg):  # made in the sensor frame, exact ground truth
            seq = with_scan_poses(seq, data_cfg, may_be_raw_sweeps=False, progress=progress)
        return seq
    seq = formats.read_sequence(data_cfg)
    if seq.poses is None:  # the scans are all there is: odometry from them, in the sensor frame
        front_end_forecast(seq.num_scans, len(seq.scans[0]) if seq.num_scans else 0, budget_s, f"{data_cfg.root}: ")
        raw = str(data_cfg.format).lower() in formats.RAW_SWEEP_FORMATS
        seq = with_scan_poses(seq, data_cfg, may_be_raw_sweeps=raw, progress=progress)
    return formats.report_missing_ground_truth(seq, data_cfg)


def load_keyframes(data_cfg, budget_s: float = 0.0) -> tuple[Sequence, Sequence]:
    """Load the sequence that `data_cfg` (config.data) names and preprocess it with the config's settings.

    Returns (loaded, keyframes): every input scan (of a recording on disk, read again from disk when used:
    data.scan_source) and the preprocessed keyframes that training uses, held in memory
    (`keyframes.source_index` indexes `loaded`). The one place where bin/train.py and bin/baseline.py turn a config
    into the scans they work on. budget_s: the run's seconds (0: no limit), for load_sequence's forecast.
    """
    loaded = load_sequence(data_cfg, budget_s=budget_s)
    return loaded, preprocess(loaded, KeyframeSettings.from_config(data_cfg))

#!/usr/bin/env python
"""Neural LiDAR bundle adjustment of one sequence.

    python bin/train.py --config=configs/demo.py                      # synthetic demo, no dataset needed
    python bin/train.py --config=configs/fusionportable.py --config.data.root=/data/canteen_day
    python bin/train.py --config=configs/generic.py:cpu --config.data.root=DIR --config.output_dir=OUT

A rerun with the same output_dir resumes from its latest checkpoint.
"""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from neld_jax.cli import main_with_config  # noqa: E402
from neld_jax.evaluate import format_table  # noqa: E402
from neld_jax.quality import format_crispness_table  # noqa: E402
from neld_jax.run import run  # noqa: E402
from neld_jax.hugepages import reexec_with_huge_page_malloc  # noqa: E402


def job(config):
    summary = run(config)
    print(f"{summary['steps']} steps in {summary['train_seconds']:.0f} s on {summary['num_scans']} keyframes of "
          f"{summary['num_input_scans']} input scans (every input scan has a refined pose); outputs in "
          f"{config.output_dir}")
    print(format_crispness_table(summary["crispness"]))
    flagged = summary["scans_report"]["flagged"]
    if flagged:
        names = ", ".join(row["file"] or f"scan {row['scan']}" for row in flagged[:5])
        print(f"{len(flagged)} keyframes flagged as outliers (residual or refinement; see scans_report.csv): {names}"
              + (" ..." if len(flagged) > 5 else ""))
    if "evaluation" in summary:
        print(format_table(summary["evaluation"]))


def init_distributed() -> None:
    """Several hosts (README, "Several devices and hosts"): NELD_JAX_COORDINATOR=host:port with
    NELD_JAX_NUM_PROCESSES and NELD_JAX_PROCESS_ID join this process to the others before jax starts, so that
    jax.devices() and the submap mesh span every host. Unset: one process, nothing to do."""
    coordinator = os.environ.get("NELD_JAX_COORDINATOR")
    if coordinator:
        import jax

        jax.distributed.initialize(coordinator_address=coordinator,
                                   num_processes=int(os.environ["NELD_JAX_NUM_PROCESSES"]),
                                   process_id=int(os.environ["NELD_JAX_PROCESS_ID"]))


if __name__ == "__main__":
    reexec_with_huge_page_malloc()  # ~25% faster CPU steps: see neld_jax/hugepages.py
    init_distributed()
    main_with_config(job)

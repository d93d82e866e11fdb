"""neld-train (bin/train.py): neural LiDAR bundle adjustment of one sequence.

    neld-train --config=configs/demo.py                      # synthetic demo, no dataset needed
    neld-train --config=configs/generic.py --config.data.root=DIR --config.output_dir=OUT
    neld-train --config=configs/lio_keyframes.py:paper --config.data.root=/data/HKU_1_bag   # the paper's schedule

No budget named: cpu (within 10 minutes on 2 cores), or gpu where JAX's default backend is a GPU (neld_jax.config).

A rerun with the same output_dir and configuration resumes from its latest checkpoint; a rerun of another
configuration into it stops with one line naming the fields that differ, and changes nothing there (docs/design.md,
"Resume"). --restart deletes the earlier run's files from output_dir (the log names them) and starts over.

Several hosts: NELD_JAX_COORDINATOR=host:port with NELD_JAX_NUM_PROCESSES and NELD_JAX_PROCESS_ID join this process
to the others before jax starts, so that the submaps' mesh spans every host's devices.
"""

import logging
import os

from absl import flags

from neld_jax.cli import main_with_config

RESTART = flags.DEFINE_bool(
    "restart",
    False,
    "Delete the files an earlier run wrote into output_dir (config.json, "
    "checkpoints, outputs) and start over, instead of resuming it.",
)


def job(config) -> None:
    from neld_jax.config import slow_run_warning
    from neld_jax.judging.judge import format_crispness_table
    from neld_jax.run import run
    from neld_jax.writing.evaluate import format_table

    if slow := slow_run_warning(config):  # e.g. :paper on a CPU: weeks
        logging.getLogger(__name__).warning(slow)
    summary = run(config, restart=RESTART.value)
    r = summary["run"]
    print(
        f"{r['steps']} steps in {r['train_seconds']:.0f} s on {r['num_scans']} keyframes of {r['num_input_scans']} "
        f"input scans (every input scan has a refined pose), started from the {r['started_from']} poses; outputs "
        f"in {config.output_dir}"
    )
    print(format_crispness_table(summary["crispness"]))
    flagged = summary["scans_report"]["flagged"]
    if flagged:
        names = ", ".join(row["file"] or f"scan {row['scan']}" for row in flagged[:5])
        print(
            f"{len(flagged)} keyframes flagged (residual or refinement; see scans_report.csv): {names}"
            + (" ..." if len(flagged) > 5 else "")
        )
    if "evaluation" in summary:
        print(format_table(summary["evaluation"]))


def init_distributed() -> None:
    """Join the other hosts' processes (NELD_JAX_COORDINATOR, NELD_JAX_NUM_PROCESSES, NELD_JAX_PROCESS_ID), if set."""
    coordinator = os.environ.get("NELD_JAX_COORDINATOR")
    if coordinator:
        import jax

        jax.distributed.initialize(
            coordinator_address=coordinator,
            num_processes=int(os.environ["NELD_JAX_NUM_PROCESSES"]),
            process_id=int(os.environ["NELD_JAX_PROCESS_ID"]),
        )


def main() -> None:
    from neld_jax.hugepages import reexec_with_huge_page_malloc

    reexec_with_huge_page_malloc()  # ~25% faster CPU steps: neld_jax/hugepages.py
    init_distributed()
    main_with_config(job, __doc__)


if __name__ == "__main__":
    main()

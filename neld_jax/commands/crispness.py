"""neld-crispness (bin/crispness.py): which trajectory gives the crispest map? Judge any poses of a sequence's scans
without ground truth.

    neld-crispness --config=configs/lio_keyframes.py:cpu --config.data.root=/data/HKU_1_bag \\
        --poses=sc_pgo=/data/HKU_1_bag/optimized_poses.txt,neld_ba=runs/hku1 --out=judged.json

Loads and preprocesses the sequence exactly like neld-train with the same config string (the same keyframes, range
crop and voxel grid, so the figures equal the run's), reads each --poses file (TUM, KITTI or Newer College CSV,
sensor -> world like the sequence's own pose file; a run's output folder stands for its poses_optimized.txt),
matches it to the keyframes (by time when the file and the scans have timestamps, else by order: one pose per input
scan or per keyframe) and measures the raw map of the keyframes under each and under the sequence's own poses
("input"): mean map entropy and plane thickness, then the crispest one's margin to each other over
eval.crispness_draws draws of the query points, "crisper on every draw" or "a tie" (docs/evaluation.md).
"""

import os

from absl import flags

from neld_jax.cli import main_with_config

POSES = flags.DEFINE_list(
    "poses",
    [],
    "Trajectories to judge, NAME=PATH or PATH (named by its file name; a run's "
    "output folder stands for its poses_optimized.txt), comma-separated; the sequence's own "
    "poses are always judged too, as 'input'.",
)
OUT = flags.DEFINE_string("out", "", "JSON file with every figure (none if empty).")


def named_paths(items: list[str]) -> dict[str, str]:
    """{name: path} of --poses items NAME=PATH or PATH; a repeated name, the reserved 'input' or a missing file is an
    error (before the scans are read)."""
    from neld_jax.errors import ConfigError, DataError

    named = {}
    for item in items:
        stem = os.path.splitext(os.path.basename(item))[0]
        name, _, path = item.partition("=") if "=" in item else (stem, "", item)
        if not name or not path:
            raise ConfigError(f"--poses item {item!r}: expected NAME=PATH or PATH")
        if name in named or name == "input":
            taken = "given twice" if name in named else "the sequence's own poses"
            raise ConfigError(f"--poses: the name {name!r} is {taken}; name each file with NAME=PATH")
        if os.path.isdir(path):  # a run's output folder: its answer
            path = os.path.join(path, "poses_optimized.txt")
        if not os.path.isfile(path):
            raise DataError(f"{path}: trajectory file does not exist (--poses {name})")
        named[name] = path
    return named


def job(config) -> None:
    from neld_jax.errors import ConfigError
    from neld_jax.judging import judge
    from neld_jax.steps.inputs import load_keyframes
    from neld_jax.writing.evaluate import trajectory_at_keyframes
    from neld_jax.writing.export import write_json

    paths = named_paths(POSES.value)
    if not paths:
        raise ConfigError("--poses: give at least one trajectory to judge against the sequence's own poses")
    loaded, keyframes = load_keyframes(config.data)
    methods = {"input": keyframes.poses}
    for name, path in paths.items():
        methods[name] = trajectory_at_keyframes(
            path, loaded, keyframes, tol=float(config.data.timestamp_tol_s), invert=bool(config.data.invert_poses)
        )
    verdict = judge.judge_trajectories(keyframes, methods, config.eval, progress=True)
    print(
        f"{keyframes.num_scans} keyframes of {loaded.num_scans} input scans ({config.data.root or config.data.format})"
    )
    print(judge.format_crispness_table(verdict["crispness"], ordered=True, digits=4))
    print(f"crispest: {verdict['crispest']}")
    for other, margin in verdict["margins"].items():
        print(judge.describe_margin(other, margin, against=verdict["crispest"]))
    if OUT.value:
        write_json(
            OUT.value,
            {
                "root": str(config.data.root),
                "input_scans": loaded.num_scans,
                "keyframes": keyframes.num_scans,
                "trajectories": {"input": "the sequence's own poses", **paths},
                **verdict,
            },
            merge=False,
        )
        print(f"written to {OUT.value}")


def main() -> None:
    main_with_config(job, __doc__)


if __name__ == "__main__":
    main()

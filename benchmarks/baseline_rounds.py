#!/usr/bin/env python
"""How the classical baseline's multi-view refinement converges, round by round, from a real sequence's recorded
odometry and from the same odometry with drift injected: whether more rounds bring the two starts' answers together
(the drift test's "within 2 cm of the answer from the recorded odometry") and how the raw map's crispness moves.

    python benchmarks/baseline_rounds.py --root=<output>/HKU_MB_2020-09-20-13-34-51_bag --rounds=10 --keep_tilt \\
        --out=/tmp/baseline_rounds.json

One baseline per start (configs/lio_keyframes.py's settings, cpu budget, the same for both starts), with --rounds
rounds of refinement (baseline.map_rounds); after each round r: "apart_cm", the ATE (SE(3)-aligned) between the two
starts' answers after r rounds; the largest move of a scan in that round; every --judge_every rounds the raw map's
mean map entropy under each answer. Round 0 is where the refinement starts (the crisper of the baseline's pose graph
and chain, which the baseline chooses, as whether its chain keeps the input's tilt: "decided" records both). The
drift is applied to the loaded keyframes in memory (benchmarks/real_data.py writes and reloads a copy; with every
scan a keyframe, as configs/lio_keyframes.py has it, the poses are the same). Nothing is trained.

--regraph: then, from each start's answer after the last round, the pose graph once more (chain links from that
answer, loop closures registered again) and the default two rounds after it; "regraph" reports the apart and the
entropy after the graph and after its rounds: whether a global solve from two nearby answers brings them together.
"""

import json
import logging
import os
import time

import harness  # this folder's benchmarks/harness.py: --out, the machine stamp and the JSON schema
from absl import app, flags

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

ROOT = flags.DEFINE_string("root", None, "One sequence folder in the lio_keyframes layout (Scans/, odom_poses.txt).")
ROUNDS = flags.DEFINE_integer("rounds", 10, "Rounds of multi-view refinement (baseline.map_rounds).")
JUDGE_EVERY = flags.DEFINE_integer("judge_every", 2, "Measure the maps' entropy every this many rounds.")
DRIFT_TRANS = flags.DEFINE_float("drift_trans_m", 0.05, "Injected drift per keyframe: translation sigma [m].")
DRIFT_ROT = flags.DEFINE_float("drift_rot_deg", 0.5, "Injected drift per keyframe: rotation sigma [deg].")
SEED = flags.DEFINE_integer("seed", 0, "Seed of the injected drift.")
KEEP_TILT = flags.DEFINE_bool(
    "keep_tilt",
    False,
    "Drift in position and heading only, as an IMU-aided odometry drifts (benchmarks/real_data.py --keep_tilt).",
)
REGRAPH = flags.DEFINE_bool(
    "regraph",
    False,
    "After the rounds, the pose graph again from each answer and two rounds after it (module docstring).",
)
harness.default_out("outputs/baseline_rounds.json")
flags.mark_flag_as_required("root")


def _config():
    from neld_jax.config import from_file

    c = from_file(os.path.join(REPO, "configs", "lio_keyframes.py"), "cpu")
    c.data.root = ROOT.value
    c.baseline.map_rounds = ROUNDS.value
    return c


def _rounds(seq, config) -> tuple[list, float, dict]:
    """-> (poses [K, 4, 4] after rounds 0 .. --rounds, the baseline's seconds, what it decided: the chain's tilt
    and where the refinement started)."""
    from neld_jax.baseline import BaselineSettings, register_sequence

    history = []
    t0 = time.perf_counter()
    result = register_sequence(
        seq.scans, seq.poses, BaselineSettings.from_config(config), on_round=lambda r, poses: history.append(poses)
    )
    return history, time.perf_counter() - t0, {"tilt": result.tilt, "refined_from": result.refined_from}


def _regraph(clouds: list, config, poses):
    """The pose graph built again from poses [K, 4, 4] (its chain links are their relative poses), then two rounds of
    refinement -> (graph's poses, after the rounds), both re-anchored on scan 0 as register_sequence does.
    clouds: baseline.prepare_clouds of the keyframes."""
    import dataclasses

    import open3d as o3d

    from neld_jax import baseline

    settings = dataclasses.replace(baseline.BaselineSettings.from_config(config), map_rounds=2)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        graph, _ = baseline.loop_closed_graph(clouds, poses, settings)
        graph = baseline.anchored(graph, poses[0])
        refined, _ = baseline.refine_against_map(clouds, graph, settings)
    return graph, baseline.anchored(refined, poses[0])


def main(argv):
    del argv
    import numpy as np

    from neld_jax.judging import judge
    from neld_jax.judging.metrics import ate
    from neld_jax.steps.inputs import load_keyframes
    from neld_jax.synthetic.pseudo_gt import with_drift

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    config = _config()
    _, seq = load_keyframes(config.data)
    recorded, recorded_s, recorded_decided = _rounds(seq, config)
    drifted_seq = with_drift(seq, DRIFT_TRANS.value, DRIFT_ROT.value, SEED.value, KEEP_TILT.value)
    drifted, drifted_s, drifted_decided = _rounds(drifted_seq, config)
    rows = []
    for r in range(ROUNDS.value + 1):
        row = {"rounds": r, "apart_cm": round(100 * ate(drifted[r], recorded[r], align="se3")["translation_rmse_m"], 3)}
        if r:
            for name, history in (("recorded", recorded), ("drift", drifted)):
                moved = np.linalg.norm(history[r][:, :3, 3] - history[r - 1][:, :3, 3], axis=1)
                row[f"largest_move_{name}_mm"] = round(1000 * float(moved.max()), 2)
        if r % JUDGE_EVERY.value == 0 or r == ROUNDS.value:
            summary, _ = judge.map_crispness(seq, {"recorded": recorded[r], "drift": drifted[r]}, config.eval)
            row.update({f"entropy_{name}": round(summary[name]["mean_map_entropy"], 4) for name in summary})
        print(json.dumps(row), flush=True)
        rows.append(row)
    regraph = {}
    if REGRAPH.value:
        from neld_jax.baseline import BaselineSettings, prepare_clouds

        # the two starts share their scans: prepared once
        clouds = prepare_clouds(seq.scans, BaselineSettings.from_config(config))
        again = {"recorded": _regraph(clouds, config, recorded[-1]), "drift": _regraph(clouds, config, drifted[-1])}
        for k, stage in enumerate(("graph", "graph_rounds")):
            poses = {name: result[k] for name, result in again.items()}
            summary, _ = judge.map_crispness(seq, poses, config.eval)
            regraph[stage] = {
                "apart_cm": round(100 * ate(poses["drift"], poses["recorded"], align="se3")["translation_rmse_m"], 3),
                **{f"entropy_{name}": round(summary[name]["mean_map_entropy"], 4) for name in summary},
            }
        print(json.dumps({"regraph": regraph}), flush=True)
    harness.write(
        harness.OUT.value,
        {
            "sequence": os.path.basename(os.path.normpath(ROOT.value)),
            "keep_tilt": KEEP_TILT.value,
            "drift_per_keyframe": {"trans_m": DRIFT_TRANS.value, "rot_deg": DRIFT_ROT.value, "seed": SEED.value},
            "baseline_s": {"recorded": round(recorded_s, 1), "drift": round(drifted_s, 1)},
            "decided": {"recorded": recorded_decided, "drift": drifted_decided},
            "date": time.strftime("%Y-%m-%d"),
            "rounds": rows,
            **({"regraph": regraph} if regraph else {}),
        },
    )


if __name__ == "__main__":
    app.run(main)

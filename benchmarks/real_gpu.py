#!/usr/bin/env python
"""Real recordings on the gpu budget, on a GPU image without open3d: prepare here, train there, judge here.

    python benchmarks/real_gpu.py --prepare --run_dir=runs/hku1              # here: .gpu_data/hku1.pkl
    bash benchmarks/real_gpu.sh [--max_train_s=150] [--budget_s=480]          # there: $OUT/<name>_trained.npz
    bash benchmarks/real_gpu.sh --set=seed=1 --out_dir=$OUT/seed1             # a variant of the same
    python benchmarks/real_gpu.py --evaluate --run_dir=runs/hku1 --trained=DIR/hku1_trained.npz \
        --out_dir=runs/hku1_gpu                                               # here: poses files, margins JSON

A run reads PCD files and runs the classical baseline with open3d, which a GPU image may lack (it is too large to
carry there); only training needs the GPU. --prepare takes a finished bin/train.py run of a sequence (any budget:
its config.json names the sequence, its start_poses.npz holds the start the run chose, the classical baseline's
poses or the input's) and writes what the gpu budget's training needs: the keyframes' training rays as sensor-frame
points (the same seeded subset a run draws), the start, and the config of configs/lio_keyframes.py:gpu with the
pose steps a run takes from that start (neld_jax.steps.start). The default mode trains every prepared sequence there
with neld_jax.steps.refine.refine_keyframes, the step a run takes (it plans the cubes from the prepared points on the
devices it finds), one after the other, and writes the keyframes' poses and the training's figures. --evaluate
measures here, on the whole preprocessed keyframes, the raw map's crispness under the input's, the baseline's, the
GPU's and the given run's own poses over eval.crispness_draws query draws, and writes poses_<method>.kitti / .txt
for every input scan, as a run does.
"""

from __future__ import annotations

import glob
import json
import logging
import os
import pickle
import tempfile
import time

import numpy as np
from absl import app, flags
from packed_points import pack_points, unpack_points  # this folder's benchmarks/packed_points.py

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

logger = logging.getLogger("real_gpu")
PREPARE = flags.DEFINE_bool("prepare", False, "Write --run_dir's sequence and start to --data (needs open3d).")
EVALUATE = flags.DEFINE_bool("evaluate", False, "Judge --trained against --run_dir's poses (needs open3d).")
RUN_DIR = flags.DEFINE_string("run_dir", "", "A finished bin/train.py run (config.json, start_poses.npz).")
NAME = flags.DEFINE_string("name", "", "The prepared sequence's name (default: --run_dir's folder name).")
DATA = flags.DEFINE_string("data", os.path.join(REPO, ".gpu_data"), "Folder of the prepared sequences.")
CONFIG = flags.DEFINE_string(
    "config", "configs/lio_keyframes.py", "The config file the run used (its get_config; relative to the repository)."
)
BUDGET = flags.DEFINE_string("budget", "gpu", "The budget of --config to train with.")
SET = flags.DEFINE_multi_string(
    "set",
    [],
    "Config overrides KEY=VALUE (neld_jax.config.apply_overrides): with "
    "--prepare on the run's config, in training on the prepared one (a variant; the "
    "pose steps stay the prepared ones).",
)
TRAINED = flags.DEFINE_string("trained", "", "--evaluate: a <name>_trained.npz the GPU wrote.")
OUT_DIR = flags.DEFINE_string(
    "out_dir",
    "",
    "--evaluate: folder for the poses files and evaluation.json; "
    "training: folder for <name>_trained.npz and real_gpu.json (default $OUT).",
)
NAMES = flags.DEFINE_list("names", [], "Training: the prepared sequences to train, in this order (default: all).")
MAX_TRAIN_S = flags.DEFINE_float(
    "max_train_s", 150.0, "Training: each sequence's training time, seconds (the schedule is compressed to it)."
)
BUDGET_S = flags.DEFINE_float("budget_s", 480.0, "Training: start no sequence after this many seconds.")


# What names the run's sequence in its config.json's data section; the budget sets the rest of the section.
SEQUENCE_KEYS = ("format", "root", "drop_unmatched_tail", "initial_poses", "first_scan", "max_scans", "synthetic")


def run_config(run_dir: str, config_file: str, budget: str, overrides: list):
    """config_file's get_config(budget) on the run's sequence (SEQUENCE_KEYS of its data section), with overrides."""
    from neld_jax.config import apply_overrides, from_file

    with open(os.path.join(run_dir, "config.json")) as f:
        data = json.load(f)["data"]
    config = from_file(os.path.join(REPO, config_file), budget)
    for key in SEQUENCE_KEYS:
        if isinstance(data.get(key), dict):
            config.data[key].update(data[key])
        elif key in data:
            config.data[key] = data[key]
    return apply_overrides(config, overrides)


def read_start(run_dir: str, input_poses: np.ndarray) -> tuple[np.ndarray, str, np.ndarray | None]:
    """The start a run trained from: (its poses [K, 4, 4], "baseline" | "input", the baseline's poses or None). A
    run whose baseline did not run saved none (neld_jax.steps.start.Start.save) and started from its input."""
    from neld_jax.steps.start import FILE

    path = os.path.join(run_dir, FILE)
    if not os.path.isfile(path):
        return input_poses, "input", None
    with np.load(path) as saved:
        meta = json.loads(str(saved["meta"]))
        saved_input = saved["input_poses"]
        if saved_input.shape != np.shape(input_poses) or not np.allclose(saved_input, input_poses, rtol=0.0, atol=1e-9):
            raise SystemExit(f"{path}: its input poses are not this sequence's keyframes (another sequence's run?)")
        return saved["poses"], meta["chosen"], saved["baseline_poses"]


def pose_steps_for(config, keyframes, chosen: str, start_poses: np.ndarray):
    """The pose steps a run takes from its start (neld_jax.steps.start): the config's own from the input; from the
    baseline's poses capped, with the prior (heavier where the start's map is thinner than start.THIN_MAP_M) and
    the start's scale kept."""
    from neld_jax.judging import judge
    from neld_jax.steps.start import pose_steps_from_baseline
    from neld_jax.training.train import PoseSteps

    if chosen != "baseline":
        return PoseSteps.from_config(config)
    judged, _ = judge.map_crispness(keyframes, {"baseline": start_poses}, config.eval)
    return pose_steps_from_baseline(config.start, config.train, judged["baseline"].get("mean_plane_thickness_m"))


def prepared_keyframes(d: dict):
    """The keyframes of a prepared file: the training rays as sensor-frame points, the input poses."""
    from neld_jax.data.sequence import Sequence

    scans = np.split(unpack_points(d["points"]), np.cumsum(d["counts"])[:-1])
    return Sequence(scans=scans, poses=d["poses"], timestamps=d["timestamps"], name=d["name"], source=d["source"])


def prepare(run_dir: str, name: str) -> dict:
    """Write DATA/<name>.pkl: what refine_keyframes needs, the keyframes' training rays as sensor-frame points."""
    import dataclasses

    from neld_jax.field.normalize import Normalization
    from neld_jax.steps.inputs import load_keyframes
    from neld_jax.training import submaps
    from neld_jax.training.rays import build_rays

    config = run_config(run_dir, CONFIG.value, BUDGET.value, SET.value)
    _, keyframes = load_keyframes(config.data)
    T_start, chosen, _ = read_start(run_dir, keyframes.poses)
    pose_steps = pose_steps_for(config, keyframes, chosen, T_start)
    rays = build_rays(
        keyframes, Normalization(1.0), max_rays_per_scan=(config.data.max_rays_per_scan or None), seed=config.seed
    )
    prepared = {
        "name": name,
        "config": config.to_dict(),
        "chosen": chosen,
        "T_start": T_start,
        "pose_steps": pose_steps.to_dict(),
        "poses": keyframes.poses,
        "timestamps": keyframes.timestamps,
        "source": keyframes.source,
        "points": pack_points(rays.directions * rays.ranges[:, None]),
        "counts": np.bincount(rays.scan_index, minlength=keyframes.num_scans),
    }
    # The plan the training will make on one device (it plans on the devices it finds)
    plan = submaps.plan_from_config(dataclasses.replace(prepared_keyframes(prepared), poses=T_start), config)
    os.makedirs(DATA.value, exist_ok=True)
    path = os.path.join(DATA.value, f"{name}.pkl")
    with open(path, "wb") as f:
        pickle.dump(prepared, f, protocol=pickle.HIGHEST_PROTOCOL)
    return {
        "path": path,
        "keyframes": keyframes.num_scans,
        "rays": int(rays.num_rays),
        "start": chosen,
        "submaps": plan.num_submaps,
        "megabytes": round(os.path.getsize(path) / 1e6, 1),
    }


def add_missing_fields(config, defaults, prefix: str = "") -> list:
    """Give `config` (in place) every field of `defaults` it lacks, with the default's value: a file prepared
    before a field existed then trains as the code does now and takes --set on the new field. Returns their keys."""
    import copy

    import ml_collections

    added = []
    for key, value in defaults.items():
        if key not in config:
            config[key] = copy.deepcopy(value)
            added.append(prefix + key)
        elif isinstance(value, ml_collections.ConfigDict) and isinstance(config[key], ml_collections.ConfigDict):
            added += add_missing_fields(config[key], value, f"{prefix}{key}.")
    return added


def train_prepared(path: str, out_dir: str, max_seconds: float) -> dict:
    """Train one prepared sequence as a run would (neld_jax.steps.refine.refine_keyframes); writes
    OUT/<name>_trained.npz."""
    import jax
    import ml_collections

    from neld_jax.config import apply_overrides, defaults
    from neld_jax.steps import refine
    from neld_jax.training.train import PoseSteps
    from neld_jax.writing import outputs

    with open(path, "rb") as f:
        d = pickle.load(f)
    # --set here makes a variant of the prepared config (one prepared file, several trainings: --out_dir each)
    config = ml_collections.ConfigDict(d["config"])
    added = add_missing_fields(config, defaults())
    config = apply_overrides(config, SET.value)
    keyframes = prepared_keyframes(d)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch:  # its checkpoints
        context = refine.TrainingContext(scratch, outputs.config_hash(config), max_seconds, progress=False)
        refined = refine.refine_keyframes(
            refine.TrainingSettings.from_config(config), keyframes, d["T_start"], PoseSteps(**d["pose_steps"]), context
        )
    wall_s = time.perf_counter() - t0
    result = refined.result
    figures = {
        "name": d["name"],
        "device": str(jax.devices()[0]),
        "jax": jax.__version__,
        "keyframes": keyframes.num_scans,
        "rays": int(refined.rays_per_keyframe.sum()),
        "start": d["chosen"],
        "submaps": int((refined.plan.weight > 0).sum()),
        "steps": int(result.state.step),
        "schedule_steps": int(result.schedules.total_steps),
        "overrides": list(SET.value),
        "defaults_added": added,
        "stopped_early": bool(result.stopped_early),
        "train_seconds": round(result.train_seconds, 2),
        "wall_seconds_with_compile": round(wall_s, 2),
        "final": result.history[-1] if result.history else {},
    }
    np.savez(
        os.path.join(out_dir, f"{d['name']}_trained.npz"), T_opt=refined.poses, figures=np.array(json.dumps(figures))
    )
    return figures


def train_all(out_dir: str) -> list:
    """Train every prepared sequence (NAMES order) while BUDGET_S lasts; real_gpu.json after each."""
    t0 = time.perf_counter()
    names = NAMES.value or sorted(os.path.basename(p)[:-4] for p in glob.glob(os.path.join(DATA.value, "*.pkl")))
    done = []
    for name in names:
        if time.perf_counter() - t0 > BUDGET_S.value:
            done.append({"name": name, "skipped": f"--budget_s={BUDGET_S.value:g} spent"})
            continue
        try:
            done.append(train_prepared(os.path.join(DATA.value, f"{name}.pkl"), out_dir, MAX_TRAIN_S.value))
        except Exception as e:  # noqa: BLE001 (one sequence's failure is recorded; the next one runs)
            logger.exception("%s failed", name)
            done.append({"name": name, "error": f"{type(e).__name__}: {e}"})
        logger.info("%s", json.dumps(done[-1]))
        with open(os.path.join(out_dir, "real_gpu.json"), "w") as f:
            json.dump(done, f, indent=1)
    return done


def evaluate(run_dir: str, trained_path: str, out_dir: str) -> dict:
    """The raw map's crispness under each method's keyframe poses, over the query draws; poses files for every input
    scan in out_dir (as a run writes them), evaluation.json with the figures."""
    from neld_jax.data.poses import read_kitti
    from neld_jax.judging import judge
    from neld_jax.steps.inputs import load_keyframes
    from neld_jax.trajectory import propagate_corrections
    from neld_jax.writing import export

    config = run_config(run_dir, CONFIG.value, BUDGET.value, SET.value)
    loaded, seq = load_keyframes(config.data)
    _, chosen, baseline = read_start(run_dir, seq.poses)
    saved = np.load(trained_path)
    figures = json.loads(str(saved["figures"]))
    if saved["T_opt"].shape != seq.poses.shape:
        raise SystemExit(f"{trained_path}: {len(saved['T_opt'])} keyframe poses for {seq.num_scans} keyframes")
    methods = {"initial": seq.poses, "optimized": saved["T_opt"]}
    if baseline is not None:
        methods["baseline"] = baseline
    run_poses = os.path.join(run_dir, "poses_optimized.kitti")
    if os.path.exists(run_poses):  # the given run's own result (e.g. the cpu budget's), on the same query points
        methods["run_optimized"] = read_kitti(run_poses)[seq.loaded_index]
    crisp, _ = judge.map_crispness(seq, methods, config.eval)
    margins = judge.crispness_margins(seq, methods, config.eval, first_draw=crisp)
    for other, margin in margins.items():
        logger.info("%s: %s", figures["name"], judge.describe_margin(other, margin))
    os.makedirs(out_dir, exist_ok=True)
    export.write_poses(out_dir, "poses_initial", loaded.timestamps, loaded.poses)
    T_all = propagate_corrections(loaded.poses, seq.loaded_index, saved["T_opt"], loaded.timestamps)
    export.write_poses(out_dir, "poses_optimized", loaded.timestamps, T_all)
    if baseline is not None:
        export.write_poses(
            out_dir,
            "poses_baseline",
            loaded.timestamps,
            propagate_corrections(loaded.poses, seq.loaded_index, baseline, loaded.timestamps),
        )
    if seq.gt_poses is not None:  # a synthetic or pseudo-ground-truth sequence: the ATE too (SE(3)-aligned)
        from neld_jax.judging import metrics

        for method, poses in methods.items():
            ate = metrics.ate(poses, seq.gt_poses)
            crisp[method]["ate_m"], crisp[method]["ate_deg"] = ate["translation_rmse_m"], ate["rotation_rmse_deg"]
    result = {
        "sequence": config.data.root,
        "run_dir": run_dir,
        "started_from": chosen,
        "training": figures,
        "num_input_scans": loaded.num_scans,
        "poses_optimized_lines": len(T_all),
        "crispness": {
            m: {
                k: crisp[m][k]
                for k in ("mean_map_entropy", "mean_plane_thickness_m", "ate_m", "ate_deg")
                if k in crisp[m]
            }
            for m in crisp
        },
        "optimized_minus": margins,
    }
    export.write_json(os.path.join(out_dir, "evaluation.json"), result)
    return result


def main(argv):
    del argv
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    if PREPARE.value or EVALUATE.value:
        if not RUN_DIR.value:
            raise SystemExit("--prepare and --evaluate need --run_dir")
        if EVALUATE.value and not os.path.isfile(TRAINED.value):
            raise SystemExit(
                f"--evaluate needs --trained, a <name>_trained.npz the training wrote (got {TRAINED.value!r})"
            )
        name = NAME.value or os.path.basename(os.path.normpath(RUN_DIR.value))
        if PREPARE.value:
            print(json.dumps(prepare(RUN_DIR.value, name)))
        else:
            out_dir = OUT_DIR.value or f"{RUN_DIR.value}_{BUDGET.value}"
            print(json.dumps(evaluate(RUN_DIR.value, TRAINED.value, out_dir)))
        return
    out_dir = OUT_DIR.value or os.environ.get("OUT") or os.path.join(REPO, "benchmarks", "results")
    os.makedirs(out_dir, exist_ok=True)
    print(json.dumps(train_all(out_dir)))


if __name__ == "__main__":
    app.run(main)

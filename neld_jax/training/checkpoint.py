"""Orbax checkpoints of a training run: the whole TrainState plus JSON metadata (config hash, keyframe count, plan
of cubes, pose steps, and the training history and seconds so far, which a resumed run continues).

A rerun with the same output directory restores the latest checkpoint and continues from its step.
"""

from __future__ import annotations

import logging
import os
from typing import Any, Callable

import jax
import numpy as np
import orbax.checkpoint as ocp

from neld_jax.errors import ConfigError, DataError
from neld_jax.jsonable import to_jsonable

logger = logging.getLogger(__name__)


def _as_tree(state) -> dict:
    return {"step": state.step, "params": state.params, "opt_state": state.opt_state, "key": state.key}


class Checkpointer:
    """Saves and restores TrainStates under `directory` (kept: the `max_to_keep` latest)."""

    def __init__(self, directory: str, max_to_keep: int = 2):
        self.directory = os.path.abspath(directory)
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True)
        self._manager = ocp.CheckpointManager(self.directory, options=options)

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def save(self, state, metadata: dict) -> None:
        step = int(state.step)
        if self._manager.latest_step() == step:
            return  # already saved (e.g. the periodic save coincided with the final one)
        self._manager.save(
            step,
            args=ocp.args.Composite(state=ocp.args.StandardSave(_as_tree(state)), metadata=ocp.args.JsonSave(metadata)),
        )
        self._manager.wait_until_finished()
        logger.info("checkpoint saved at step %d in %s", step, self.directory)

    def restore(self, template_state, expected_config_hash: str | None = None, expected_data: dict | None = None):
        """Restore the latest checkpoint into the structure of `template_state`; returns (state, metadata).

        expected_data: {"num_scans": int, "normalization": {"scale", "offset"}} of the data loaded now; a
        checkpoint written for other data raises DataError before the state (whose shapes may differ) is read.
        """
        step = self._manager.latest_step()
        if step is None:
            raise FileNotFoundError(f"no checkpoint in {self.directory}")
        restored = self._manager.restore(step, args=ocp.args.Composite(metadata=ocp.args.JsonRestore()))
        metadata = dict(restored["metadata"])
        if expected_config_hash is not None and metadata.get("config_hash") != expected_config_hash:
            raise ConfigError(
                f"the checkpoint in {self.directory} was written with a different configuration "
                f"(hash {metadata.get('config_hash')} != {expected_config_hash}); use a new output_dir, or neld-train "
                f"--restart to start over"
            )
        if expected_data is not None:
            self._check_data(metadata, expected_data)
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, _as_tree(template_state))
        tree = self._manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))["state"]
        state = template_state.replace(
            step=tree["step"], params=tree["params"], opt_state=tree["opt_state"], key=tree["key"]
        )
        logger.info("resumed from the checkpoint at step %d in %s", step, self.directory)
        return state, metadata

    def _check_data(self, metadata: dict, expected: dict) -> None:
        """The same keyframes, plan of cubes (their normalisations) and pose steps, else the poses would resume in
        another frame or under another rule."""
        differences = []
        if "num_scans" in metadata and int(metadata["num_scans"]) != int(expected["num_scans"]):
            differences.append(f"{metadata['num_scans']} keyframes, now {expected['num_scans']}")
        for key, what in (("plan", "another plan of cubes"), ("pose_steps", "other pose steps")):
            if key in expected and not _same(metadata.get(key), expected[key]):
                differences.append(what)
        if differences:
            raise DataError(
                f"the checkpoint in {self.directory} was written for other data "
                f"({'; '.join(differences)}); use a new output_dir, or neld-train --restart to start over"
            )

    def close(self) -> None:
        self._manager.close()


def fit_resuming(
    directory: str,
    metadata: dict,
    initial_state: Callable[[], Any],
    fit_fn: Callable,
    on_save: Callable[[], None] | None = None,
):
    """Run fit_fn from the latest checkpoint under `directory` (or from the initial state), checkpointing as it goes.

    metadata: what every checkpoint records and a resume must match (its "config_hash" and the data's shape: scan
    count, plan of cubes, ...); a checkpoint of other data is an error rather than a resume in another frame.
    initial_state(): the state training starts from, also the template a checkpoint restores into.
    fit_fn(state, checkpoint_fn=, history=, elapsed_s=) -> its result (train.fit), given the restored state with the
    history and training seconds saved with it, or the initial state, [] and 0.
    on_save(): runs before each checkpoint is saved (the run's clock: a process killed after it loses no seconds).
    """
    ckpt = Checkpointer(directory)
    state, history, elapsed_s = initial_state(), [], 0.0
    if ckpt.latest_step() is not None:
        state, saved = ckpt.restore(state, expected_config_hash=metadata["config_hash"], expected_data=metadata)
        history, elapsed_s = list(saved.get("history", [])), float(saved.get("train_seconds", 0.0))

    def save(s, history, seconds):
        if on_save is not None:
            on_save()
        ckpt.save(s, {**metadata, "history": to_jsonable(history), "train_seconds": seconds})

    result = fit_fn(state, checkpoint_fn=save, history=history, elapsed_s=elapsed_s)
    ckpt.close()
    return result


def _same(saved, now) -> bool:
    """Whether two JSON records agree, numbers to 1e-9 (relative): a plan's scales read back from JSON."""
    if isinstance(saved, dict) and isinstance(now, dict):
        return saved.keys() == now.keys() and all(_same(saved[k], now[k]) for k in saved)
    if isinstance(saved, (list, tuple)) and isinstance(now, (list, tuple)):
        return len(saved) == len(now) and all(_same(a, b) for a, b in zip(saved, now))
    if isinstance(saved, (int, float)) and isinstance(now, (int, float)) and not isinstance(saved, bool):
        return bool(np.isclose(saved, now, rtol=1e-9, atol=1e-12))
    return saved == now

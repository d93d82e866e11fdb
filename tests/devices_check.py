"""Run by tests/test_train.py in a subprocess with XLA_FLAGS=--xla_force_host_platform_device_count=8 (the flag must
be set before jax is imported). Prints one "OK <name>" line per check; an assertion stops it."""

import os
import sys

assert "--xla_force_host_platform_device_count=8" in os.environ.get("XLA_FLAGS", ""), "run with 8 CPU devices"
os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # conftest's helpers

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from conftest import make_tiny_config, sphere_plan  # noqa: E402
from jax.sharding import PartitionSpec as P  # noqa: E402

from neld_jax.training import train  # noqa: E402
from neld_jax.training.checkpoint import Checkpointer  # noqa: E402


def main(tmp: str) -> None:
    import time

    t0 = time.perf_counter()
    assert len(jax.devices()) == 8
    cfg = make_tiny_config("", steps=10)
    cfg.train.fixed_scans = ()
    cfg.train.c2f_end_fraction = 0.0  # poses move from step 0, so the pose updates are compared too
    cfg.sampling.coarse_stages, cfg.sampling.fine_stages = (8,), (4,)
    num_scans = 17
    # 17 keyframes in windows of 3 sharing 1: 8 submaps (starts 0, 2, ..., 14), one per device.
    rays8, frames8, plan, T = sphere_plan(num_scans, 48, window=3, num_devices=8)
    rays1, frames1, _, _ = sphere_plan(num_scans, 48, window=3, num_devices=1)
    assert plan.num_submaps == 8 and plan.weight.min() == 1
    steps = train.PoseSteps.from_config(cfg)

    # 1. The sharded step equals the unsharded one to float32 precision, over 3 steps.
    one = train.make_trainer(cfg, num_scans, 8, steps, T, mesh=train.make_mesh(1))
    eight = train.make_trainer(cfg, num_scans, 8, steps, T, mesh=train.make_mesh(8))
    step1 = jax.jit(one.step, static_argnames=("sampler",))
    step8 = jax.jit(eight.step, static_argnames=("sampler",))
    sampler = one.sampler(0)
    a, b = train.init_state(cfg, one, num_scans, 8), train.init_state(cfg, eight, num_scans, 8)
    for _ in range(3):
        a, ma = step1(a, rays1, frames1, sampler)
        b, mb = step8(b, rays8, frames8, sampler)
    for (path, x), y in zip(jax.tree_util.tree_flatten_with_path(a.params)[0], jax.tree.leaves(b.params)):
        np.testing.assert_allclose(
            np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6, err_msg=jax.tree_util.keystr(path)
        )
    np.testing.assert_allclose(float(ma["loss"]), float(mb["loss"]), rtol=1e-5)
    assert np.abs(np.asarray(a.params["poses"])).max() > 0  # the poses moved, so they were compared too
    field_leaf = jax.tree.leaves(b.params["fields"])[0]
    assert field_leaf.sharding.spec == P("submaps") and len(field_leaf.sharding.device_set) == 8
    assert b.params["poses"].sharding.is_fully_replicated
    print("OK sharded step equals unsharded", f"({time.perf_counter() - t0:.1f} s)")

    # 2. A scan shared by two submaps: one row of poses whose gradient is the sum of both submaps' contributions.
    loss_fn = train.make_loss(one.field, train.loss_settings(cfg, 8), 32)
    key, alpha = jax.random.PRNGKey(3), jnp.float32(4.0)
    params = a.params

    @jax.jit
    def pose_grad_of(weight):
        f = frames1._replace(weight=weight)
        return jax.grad(lambda p: loss_fn(p, rays1, f, key, alpha, sampler)[0])(params)["poses"]

    def pose_grad(weight):
        return np.asarray(pose_grad_of(jnp.asarray(weight, jnp.float32)))

    both = pose_grad(plan.weight)
    alone = [pose_grad(np.eye(plan.num_submaps)[m] * plan.weight[m]) for m in range(plan.num_submaps)]
    np.testing.assert_allclose(both, np.sum(alone, axis=0), rtol=1e-4, atol=1e-7)
    shared = 2  # keyframe 2 is the last of window [0, 3) and the first of window [2, 5)
    assert list(np.flatnonzero([(row == shared).any() for row in plan.members])) == [0, 1]
    assert np.abs(alone[0][shared]).max() > 0 and np.abs(alone[1][shared]).max() > 0
    assert both.shape == (num_scans, 6)
    print("OK shared scan gradient is the sum of its submaps'", f"({time.perf_counter() - t0:.1f} s)")

    # 3. Resume with sharded state: save at step 3, two more steps, against restore-then-two-steps.
    ckpt = Checkpointer(os.path.join(tmp, "ckpt"))
    ckpt.save(b, {"num_scans": num_scans})
    c = b
    for _ in range(2):
        c, _ = step8(c, rays8, frames8, sampler)
    restored, _ = ckpt.restore(train.init_state(cfg, eight, num_scans, 8))
    ckpt.close()
    assert int(restored.step) == 3
    restored_leaf = jax.tree.leaves(restored.params["fields"])[0]
    assert restored_leaf.sharding.spec == P("submaps"), restored_leaf.sharding
    d = restored
    for _ in range(2):
        d, _ = step8(d, rays8, frames8, sampler)
    for x, y in zip(jax.tree.leaves(c), jax.tree.leaves(d)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-6, atol=1e-7)
    print("OK resume with sharded state", f"({time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":
    main(sys.argv[1])

"""Cube-bounded intervals (eq. 7) against brute-force marching, coarse and fine sample placement."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neld_jax.field import sampling

Z_LOW, Z_UP = 0.05, 3.0
MARCH_STEP = 1e-3

# Jitted once (eager dispatch of many small ops is slower than compiling on 2 CPU cores).
cube_interval = jax.jit(sampling.cube_interval, static_argnums=(2, 3))
slab_intersection = jax.jit(sampling.slab_intersection)
stratified_samples = jax.jit(sampling.stratified_samples, static_argnums=2)
fine_samples_before = jax.jit(sampling.fine_samples_before, static_argnums=2)
nerf_resample = jax.jit(sampling.nerf_resample, static_argnums=2)


@pytest.fixture(autouse=True)
def _float64():
    with jax.enable_x64(True):
        yield


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _test_rays():
    """Rays of every kind: inside the cube, outside towards it, outside away from it, parallel to faces."""
    rng = np.random.default_rng(0)
    inside = rng.uniform(-0.9, 0.9, size=(16, 3)), _unit(rng.normal(size=(16, 3)))
    outside_origins = _unit(rng.normal(size=(16, 3))) * rng.uniform(1.8, 2.5, size=(16, 1))
    towards = outside_origins, _unit(-outside_origins + rng.normal(scale=0.2, size=(16, 3)))
    away = outside_origins, _unit(outside_origins)
    far = _unit(rng.normal(size=(4, 3))) * 5.0  # the cube is beyond z_up: clamped interval empty
    far_towards = far, _unit(-far)
    parallel_origins = np.array(
        [[-2.0, 0.5, 0.3], [-2.0, 1.5, 0.3], [0.2, 0.4, -0.1], [1.5, -0.3, 2.0], [0.0, 0.0, 3.0], [0.5, 0.5, 0.5]]
    )
    parallel_directions = np.array(
        [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], _unit([1, 1, 0])]
    )
    groups = [inside, towards, away, far_towards, (parallel_origins, parallel_directions)]
    return np.concatenate([g[0] for g in groups]), np.concatenate([g[1] for g in groups])


def _brute_force_interval(origins, directions, max_range=12.0):
    """[first, last] z on a fine grid where o + z d lies in [-1, 1]^3 and in [z_low, z_up]; None if nowhere."""
    z = np.arange(0.0, max_range, MARCH_STEP)
    result = []
    for o, d in zip(origins, directions):
        points = o[None] + z[:, None] * d[None]
        ok = np.all(np.abs(points) <= 1.0, axis=-1) & (z >= Z_LOW) & (z <= Z_UP)
        result.append((z[ok].min(), z[ok].max()) if ok.any() else None)
    return result


def test_cube_interval_matches_brute_force_marching():
    origins, directions = _test_rays()
    z_near, z_far = (np.asarray(a) for a in cube_interval(origins, directions, Z_LOW, Z_UP))
    assert np.all(np.isfinite(z_near)) and np.all(np.isfinite(z_far))
    expected = _brute_force_interval(origins, directions)
    kinds = {"inside": 0, "hit": 0, "fallback": 0}
    for i, interval in enumerate(expected):
        if interval is None:
            assert (z_near[i], z_far[i]) == (Z_LOW, Z_UP), f"ray {i} misses: expected the fallback"
            kinds["fallback"] += 1
        else:
            np.testing.assert_allclose([z_near[i], z_far[i]], interval, atol=2 * MARCH_STEP, err_msg=f"ray {i}")
            kinds["inside" if np.all(np.abs(origins[i]) <= 1) else "hit"] += 1
    assert min(kinds.values()) >= 4, kinds  # every kind of ray really occurred


def test_slab_intersection_parallel_rays_and_inside_origins():
    origins = np.array([[-2.0, 0.5, 0.0], [-2.0, 1.5, 0.0], [0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    directions = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    c_near, c_far, hit = (np.asarray(a) for a in slab_intersection(origins, directions))
    np.testing.assert_array_equal(hit, [True, False, True, False])  # in-slab parallel, off-slab, inside, behind
    np.testing.assert_allclose([c_near[0], c_far[0]], [1.0, 3.0])
    np.testing.assert_allclose([c_near[2], c_far[2]], [-1.0, 1.0])
    assert c_near[2] <= 0  # starting inside
    # Parallel rays give no NaN in the gradient either.
    grads = jax.grad(lambda o: jnp.sum(jnp.where(hit, sampling.slab_intersection(o, directions)[1], 0.0)))(origins)
    assert np.all(np.isfinite(grads))


def test_cube_interval_bound_argument():
    origins = np.array([[-3.0, 0.0, 0.0]])
    directions = np.array([[1.0, 0.0, 0.0]])
    z_near, z_far = sampling.cube_interval(origins, directions, 0.1, 10.0, bound=2.0)
    np.testing.assert_allclose([z_near[0], z_far[0]], [1.0, 5.0])


def test_stratified_samples_deterministic_and_jittered():
    z_near = jnp.array([0.0, 1.0, 0.5])
    z_far = jnp.array([1.0, 3.0, 0.5 + 1e-9])
    mid = stratified_samples(z_near, z_far, 4)
    np.testing.assert_allclose(mid[0], [0.125, 0.375, 0.625, 0.875])
    np.testing.assert_allclose(mid[1], [1.25, 1.75, 2.25, 2.75])
    jittered = np.asarray(stratified_samples(z_near, z_far, 4, jax.random.key(0)))
    other = np.asarray(stratified_samples(z_near, z_far, 4, jax.random.key(1)))
    assert not np.allclose(jittered, other)
    for row, (lo, hi) in enumerate(zip(np.asarray(z_near), np.asarray(z_far))):
        edges = np.linspace(lo, hi, 5)
        assert np.all(jittered[row] >= edges[:-1] - 1e-15) and np.all(jittered[row] <= edges[1:] + 1e-15)
    assert np.all(np.diff(jittered, axis=-1) >= 0)


def _coarse(num_rays=3, num_samples=8):
    z_near = jnp.full((num_rays,), 0.2)
    z_far = jnp.full((num_rays,), 1.8)
    return z_near, stratified_samples(z_near, z_far, num_samples)


def test_fine_samples_before_land_in_the_bin_before_the_weighted_sample():
    z_near, z_coarse = _coarse()
    chosen = [3, 0, 7]  # one-hot weights: interior, the first sample (bin starts at z_near), the last
    weights = jax.nn.one_hot(jnp.array(chosen), 8) * 0.9
    for key in (None, jax.random.key(2)):
        fine = np.asarray(fine_samples_before(z_coarse, weights, 16, z_near, key))
        assert fine.shape == (3, 16)
        assert np.all(np.diff(fine, axis=-1) >= 0)
        for row, i in enumerate(chosen):
            lo = float(z_near[row]) if i == 0 else float(z_coarse[row, i - 1])
            hi = float(z_coarse[row, i])
            assert np.all((fine[row] >= lo) & (fine[row] <= hi)), (row, fine[row], lo, hi)
    # Deterministic samples spread evenly across the bin (not all on its middle).
    fine = np.asarray(fine_samples_before(z_coarse, weights, 4, z_near))
    lo, hi = float(z_coarse[0, 2]), float(z_coarse[0, 3])
    np.testing.assert_allclose(fine[0], lo + (hi - lo) * (np.arange(4) + 0.5) / 4)


def test_fine_samples_before_follow_the_weights():
    z_near, z_coarse = _coarse(1)
    weights = jnp.zeros((1, 8)).at[0, 2].set(0.6).at[0, 5].set(0.2)  # 3 : 1 between bins 2 and 5
    fine = np.asarray(fine_samples_before(z_coarse, weights, 16, z_near))[0]
    in_bin_2 = (fine >= z_coarse[0, 1]) & (fine <= z_coarse[0, 2])
    in_bin_5 = (fine >= z_coarse[0, 4]) & (fine <= z_coarse[0, 5])
    assert in_bin_2.sum() == 12 and in_bin_5.sum() == 4
    many = fine_samples_before(
        jnp.tile(z_coarse, (200, 1)), jnp.tile(weights, (200, 1)), 16, jnp.tile(z_near, 200), jax.random.key(3)
    )
    fraction = np.mean((np.asarray(many) >= z_coarse[0, 1]) & (np.asarray(many) <= z_coarse[0, 2]))
    assert abs(fraction - 0.75) < 0.02


def test_fine_sampling_without_weight_is_uniform_and_finite():
    z_near, z_coarse = _coarse(2)
    for fine in (
        fine_samples_before(z_coarse, jnp.zeros((2, 8)), 16, z_near),
        nerf_resample(z_coarse, jnp.zeros((2, 8)), 12),
    ):
        fine = np.asarray(fine)
        assert np.all(np.isfinite(fine))
        assert fine.min() >= 0.2 and fine.max() <= 1.8
        assert np.ptp(fine[0]) > 1.0  # spread over the whole interval


def test_nerf_resample_places_samples_around_the_weighted_sample():
    z_near, z_coarse = _coarse()
    chosen = [3, 1, 6]
    weights = jax.nn.one_hot(jnp.array(chosen), 8)
    for key in (None, jax.random.key(4)):
        fine = np.asarray(nerf_resample(z_coarse, weights, 16, key))
        assert np.all(np.diff(fine, axis=-1) >= 0)
        for row, i in enumerate(chosen):
            lo = 0.5 * float(z_coarse[row, i - 1] + z_coarse[row, i])
            hi = 0.5 * float(z_coarse[row, i] + z_coarse[row, i + 1])
            assert np.all((fine[row] >= lo - 1e-12) & (fine[row] <= hi + 1e-12))
            assert np.any(fine[row] > z_coarse[row, i]) and np.any(fine[row] < z_coarse[row, i])


def test_fine_samples_carry_no_gradient():
    z_near, z_coarse = _coarse()
    weights = jnp.full((3, 8), 0.1)

    def total(z, w):
        return jnp.sum(sampling.fine_samples_before(z, w, 8, z_near)) + jnp.sum(sampling.nerf_resample(z, w, 8))

    grad_z, grad_w = jax.grad(total, argnums=(0, 1))(z_coarse, weights)
    np.testing.assert_array_equal(grad_z, 0.0)
    np.testing.assert_array_equal(grad_w, 0.0)


def test_merge_samples_sorts_and_returns_the_permutation():
    rng = np.random.default_rng(5)
    z_a = np.sort(rng.uniform(size=(4, 6)), axis=-1)
    z_b = np.sort(rng.uniform(size=(4, 3)), axis=-1)
    z, order = sampling.merge_samples(z_a, z_b)
    np.testing.assert_array_equal(z, np.sort(np.concatenate([z_a, z_b], -1), -1))
    values = np.concatenate([z_a * 10, z_b * 10], axis=-1)  # something computed per sample
    np.testing.assert_allclose(np.take_along_axis(values, np.asarray(order), -1), np.asarray(z) * 10)
    # Ties (and repeated values inside one set) keep z_a's samples first, as a stable argsort does.
    z_a = np.array([[0.1, 0.2, 0.2, 0.5, 0.9], [0.0, 0.0, 0.0, 0.0, 0.0]])
    z_b = np.array([[0.2, 0.5, 0.6], [0.0, 0.0, 1.0]])
    z, order = sampling.merge_samples(z_a, z_b)
    both = np.concatenate([z_a, z_b], -1)
    np.testing.assert_array_equal(order, np.argsort(both, axis=-1, kind="stable"))
    np.testing.assert_array_equal(z, np.sort(both, -1))

"""The ray orders of the mesh queries (engine.query.order) and the radix sort behind them."""
import numpy as np
import pytest

from engine.query.order import BAD_RAY_KEY, coherent_order, ray_keys_kernel, ray_order, spread_bits, spread_table
from engine.core.radix import MIN_PART, radix_argsort


@pytest.mark.parametrize("n", [0, 1, 7, 1000, 2 * MIN_PART + 13])
@pytest.mark.parametrize("top", [0, 3, 2 ** 11, 2 ** 33, 2 ** 64 - 1])
def test_radix_argsort_is_numpys_stable_argsort(n, top):
    keys = np.random.default_rng(n + top % 1000).integers(0, top, size=n, dtype=np.uint64, endpoint=True)
    before = keys.copy()
    order = radix_argsort(keys)
    assert order.dtype == np.int64
    assert np.array_equal(order, np.argsort(keys, kind="stable"))
    assert np.array_equal(keys, before)  # the caller's keys are left as given


@pytest.mark.parametrize("parts", [1, 2, 3, 7])
def test_radix_argsort_in_parts_keeps_equal_keys_in_input_order(parts):
    """The batch is cut into parts (one per thread) whose counts must combine stably: many
    equal keys spread over every part keep their input order, whatever the number of parts."""
    keys = np.repeat(np.arange(5, dtype=np.uint64)[::-1], 3 * MIN_PART)
    keys[::7] = np.uint64(2 ** 40 + 3)  # a second digit that varies
    assert np.array_equal(radix_argsort(keys, parts=parts), np.argsort(keys, kind="stable"))


@pytest.mark.parametrize("stride", range(1, 7))
def test_spread_table_is_spread_bits_of_each_byte(stride):
    table = spread_table(stride)
    assert all(table[b] == spread_bits(np.uint64(b), 8, stride) for b in range(256))


def eye_rays(n, seed=0, bad=0):
    """n rays from one eye into a 40-degree cone, in random order; the first ``bad`` get a NaN
    or zero direction."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.35, 0.35, size=(n, 2))
    directions = np.column_stack([xy, -np.ones(n)]) * rng.uniform(0.5, 2.0, size=(n, 1))
    origins = np.tile([0.1, 0.2, 3.0], (n, 1))
    directions[:bad:2] = np.nan
    directions[1:bad:2] = 0.0
    return origins, directions


def unit(d):
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_coherent_order_makes_neighbours_of_rays_from_one_eye():
    origins, directions = eye_rays(40000, bad=10)
    order = coherent_order(origins, directions, np.zeros(3), 1.0)
    assert np.array_equal(np.sort(order), np.arange(len(order)))
    assert set(order[-10:].tolist()) == set(range(10))  # bad rays last
    good = unit(directions[order[:-10]])
    shuffled_step = np.median(np.linalg.norm(np.diff(unit(directions[10:]), axis=0), axis=1))
    sorted_step = np.median(np.linalg.norm(np.diff(good, axis=0), axis=1))
    assert sorted_step < 0.02 * shuffled_step
    # Blocks of 64 sorted neighbours: each spans a small part of the cone.
    blocks = good[: len(good) // 64 * 64].reshape(-1, 64, 3)
    assert np.median(1 - np.linalg.norm(blocks.mean(axis=1), axis=1)) < 1e-3


def test_coherent_order_sorts_parallel_rays_by_origin_and_leaves_identical_rays_alone():
    rng = np.random.default_rng(1)
    origins = np.column_stack([rng.uniform(-1, 1, size=(20000, 2)), np.full(20000, 5.0)])
    directions = np.tile([0.0, 0.0, -2.0], (20000, 1))
    order = coherent_order(origins, directions, np.zeros(3), 2.0)
    step = np.median(np.linalg.norm(np.diff(origins[order], axis=0), axis=1))
    assert step < 0.02 * np.median(np.linalg.norm(np.diff(origins, axis=0), axis=1))
    same = coherent_order(np.ones((100, 3)), np.tile([0.0, 1.0, 0.0], (100, 1)), np.zeros(3), 1.0)
    assert np.array_equal(same, np.arange(100))


def test_ray_order_keys_put_bad_rays_last_with_the_radix_sort():
    origins, directions = eye_rays(5000, seed=2, bad=4)
    keys = np.empty(len(origins), np.uint64)
    ray_keys_kernel(origins, directions, np.zeros(3), 1.0, keys)
    assert (keys[:4] == BAD_RAY_KEY).all() and (keys[4:] < BAD_RAY_KEY).all()
    order = ray_order(origins, directions, np.zeros(3), 1.0)
    assert np.array_equal(order, np.argsort(keys, kind="stable"))


def test_packing_verdicts_on_batches_of_every_shape():
    """``engine.query.coherent.packing``: the caller's order for blocks tighter than the batch,
    a sort for batches from one eye, nothing for the rest (parallel sweeps included)."""
    from engine.query.coherent import MIN_RAYS, PACK_INPUT, PACK_NONE, PACK_SORTED, packing

    n = 20000
    origins, directions = eye_rays(n)
    assert packing(origins, directions, 1.0) == PACK_SORTED  # one eye, shuffled
    image = np.lexsort((directions[:, 0] / -directions[:, 2], np.round(directions[:, 1] / -directions[:, 2], 2)))
    assert packing(origins[image], directions[image], 1.0) == PACK_INPUT  # the same rays in rows
    rng = np.random.default_rng(5)
    sweep_origins = np.column_stack([rng.uniform(-1, 1, size=(n, 2)), np.full(n, 5.0)])
    sweep = np.tile([0.0, 0.0, -1.0], (n, 1))
    assert packing(sweep_origins, sweep, 1.0) == PACK_NONE  # parallel rays: origins spread, not sorted
    to_light = np.array([4.0, 5.0, 6.0]) - sweep_origins  # spread origins, one far point
    assert packing(sweep_origins, to_light, 1.0) == PACK_NONE
    scattered_o = rng.normal(size=(n, 3)) * 3
    scattered_d = rng.normal(size=(n, 3))
    assert packing(scattered_o, scattered_d, 1.0) == PACK_NONE  # spread in both
    assert packing(np.ones((n, 3)), np.tile([1.0, 0.0, 0.0], (n, 1)), 1.0) == PACK_INPUT  # one ray, n times
    assert packing(origins[: MIN_RAYS - 1], directions[: MIN_RAYS - 1], 1.0) == PACK_NONE  # too few
    assert packing(origins, np.full((n, 3), np.nan), 1.0) == PACK_NONE  # every ray bad


@pytest.mark.parametrize("varying", [1, 2, 3, 6])
def test_coherent_keys_interleave_the_varying_coordinates_bit_by_bit(varying):
    """The batch-scaled key of ``coherent_order`` against a Python interleave of the quantised
    coordinates, for one to six coordinates that vary (six: 10 bits each, where a byte table's
    third lookup would shift past 64 bits)."""
    from engine.query.order import coherent_keys_kernel, spread_table

    rng = np.random.default_rng(varying)
    n = 500
    origins = np.zeros((n, 3))
    directions = np.tile([0.0, 0.0, 1.0], (n, 1))
    axes = list(range(6))[:varying] if varying != 1 else [0]
    for k in axes:
        if k < 3:
            origins[:, k] = rng.uniform(-1, 1, n)
        else:
            directions[:, k - 3] = rng.uniform(0.5, 1.0, n)  # positive: components of the unit vector vary
    unit_d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    coords = np.column_stack([origins, unit_d])
    axes = np.array([k for k in range(6) if np.ptp(coords[:, k]) > 1e-9], np.int64)
    m = len(axes)
    bits = min(24, 60 // m)
    low = coords.min(axis=0)
    cells = np.zeros(6)
    cells[axes] = ((1 << bits) - 1) / np.ptp(coords[:, axes], axis=0)
    keys = np.empty(n, np.uint64)
    coherent_keys_kernel(origins, directions, np.zeros(3), 1.0, low, cells, axes, bits, spread_table(m), keys)
    for i in range(0, n, 37):
        expected = 0
        for j, k in enumerate(axes):
            q = min(max(int((coords[i, k] - low[k]) * cells[k] + 0.5), 0), (1 << bits) - 1)
            for b in range(bits):
                expected |= ((q >> b) & 1) << (b * m + j)
        assert int(keys[i]) == expected, (i, m)

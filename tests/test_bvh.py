"""BVH invariants, SAH quality, refit and robustness to degenerate triangles."""
import numpy as np
import pytest

from engine.core.bvh import build_bvh, node_depths
from engine.core.bvh_refit import refit_bvh, sah_cost
from engine.core.errors import ConfigError
from engine.core.scene import make_triangles
from scenes.catalog import load_named


def check_invariants(bvh, n_tris):
    leaves = np.flatnonzero(bvh.count > 0)
    covered = np.concatenate([bvh.prim[bvh.first[i]:bvh.first[i] + bvh.count[i]] for i in leaves])
    assert sorted(covered.tolist()) == list(range(n_tris)), "every primitive in exactly one leaf"
    inner = np.flatnonzero(bvh.count == 0)
    for child_offset in (0, 1):
        child = bvh.first[inner] + child_offset
        assert (child > inner).all(), "children are stored after their parent"
        assert (bvh.bmin[child] >= bvh.bmin[inner]).all() and (bvh.bmax[child] <= bvh.bmax[inner]).all()
    assert node_depths(bvh).max() == bvh.depth


def test_invariants_on_default_scene():
    tris = load_named("whitted").triangles
    bvh = build_bvh(tris, leaf_size=2, bins=32)
    check_invariants(bvh, tris.v0.shape[0])
    assert bvh.count.max() <= 2


def test_sah_beats_median_split_on_bunny(shared_scenes):
    tris = load_named("bunny").triangles
    sah, median = build_bvh(tris), build_bvh(tris, split="median")
    check_invariants(sah, tris.v0.shape[0])
    assert sah_cost(sah) <= sah_cost(median)


def test_degenerate_triangles_do_not_break_the_build():
    rng = np.random.default_rng(1)
    good = rng.random((30, 3))
    point = np.zeros((1, 3))
    line = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]])
    vertices = np.vstack([good, point, line])
    faces = np.vstack([np.arange(30).reshape(10, 3),
                       np.full((50, 3), 30),             # 50 triangles collapsed to one point
                       np.tile([31, 32, 33], (20, 1))])  # 20 zero-area slivers on a line
    tris = make_triangles(vertices, faces, 0)
    bvh = build_bvh(tris, leaf_size=4)
    check_invariants(bvh, len(faces))


def test_refit_follows_moved_vertices():
    tris = load_named("whitted").triangles
    bvh = build_bvh(tris)
    shift = np.float32(3.0)
    moved = tris._replace(v0=tris.v0 + shift, v1=tris.v1 + shift, v2=tris.v2 + shift)
    refit = refit_bvh(bvh, moved)
    np.testing.assert_allclose(refit.bmin, bvh.bmin + shift, atol=1e-5)
    np.testing.assert_array_equal(refit.first, bvh.first)
    check_invariants(refit, tris.v0.shape[0])


def test_child_order_is_cached_per_bvh_and_follows_a_refit():
    """Packet traversals take the near-child table from a per-BVH cache: the kernel's answer,
    computed once, and computed again for a refit BVH (new arrays), whose order may differ."""
    from engine.packet.kernels import child_order_keys
    from engine.packet.plugin import cached_child_order

    tris = load_named("whitted").triangles
    bvh = build_bvh(tris)
    keys = cached_child_order(bvh)
    np.testing.assert_array_equal(keys, child_order_keys(bvh.bmin, bvh.bmax, bvh.first, bvh.count))
    assert cached_child_order(bvh) is keys
    mirror = np.array([-1, 1, 1], np.float32)  # left and right swap along x
    mirrored = refit_bvh(bvh, tris._replace(v0=tris.v0 * mirror, v1=tris.v1 * mirror, v2=tris.v2 * mirror))
    fresh = child_order_keys(mirrored.bmin, mirrored.bmax, mirrored.first, mirrored.count)
    assert (fresh != keys).any()
    np.testing.assert_array_equal(cached_child_order(mirrored), fresh)


def test_bad_build_parameters_are_config_errors():
    tris = load_named("whitted").triangles
    with pytest.raises(ConfigError, match="leaf_size"):
        build_bvh(tris, leaf_size=0)
    with pytest.raises(ConfigError, match="bins"):
        build_bvh(tris, bins=1)

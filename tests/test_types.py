"""Contracts: field names, dtypes, shapes and contiguity of what the core produces."""
import numpy as np
import pytest

from engine.core import types
from engine.core.bvh import build_bvh
from scenes.catalog import load_named

from conftest import primary_batch


def test_triangles_contract():
    tris = load_named("whitted").triangles
    assert types.Triangles._fields[:4] == ("v0", "e1", "e2", "ng")
    t = tris.v0.shape[0]
    for name in ("v0", "e1", "e2", "ng", "v1", "v2"):
        array = getattr(tris, name)
        assert array.dtype == np.float32 and array.shape == (t, 3) and array.flags.c_contiguous, name
    assert tris.material.dtype == np.int32 and tris.material.shape == (t,)
    assert tris.normals.shape == (t, 3, 3)  # the spheres carry smooth normals
    np.testing.assert_allclose(tris.v0 + tris.e1, tris.v1, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(tris.ng, axis=1), 1.0, atol=1e-5)


def test_bvh_rays_packets_hits_contract():
    scene = load_named("whitted")
    bvh = build_bvh(scene.triangles)
    assert bvh.bmin.dtype == np.float32 and bvh.bmin.shape == bvh.bmax.shape == (len(bvh.first), 3)
    assert bvh.first.dtype == bvh.count.dtype == bvh.prim.dtype == np.int32
    assert bvh.build_seconds > 0 and 0 < bvh.depth < types.MAX_BVH_DEPTH
    rays, packets = primary_batch(scene, 30, 22, 8)
    r = rays.org.shape[0]
    for name in ("org", "dir", "inv_dir"):
        assert getattr(rays, name).dtype == np.float32 and getattr(rays, name).shape == (r, 3)
    assert rays.pixel.dtype == np.int32 and rays.kind == "primary"
    assert np.isfinite(rays.inv_dir).all()
    offsets = packets.offsets
    assert offsets[0] == 0 and offsets[-1] == r and (np.diff(offsets) % 4 == 0).all()
    assert sorted(rays.pixel[rays.pixel >= 0].tolist()) == list(range(30 * 22))
    dead = rays.pixel < 0
    assert (rays.tmax[dead] < rays.tmin[dead]).all()
    hits = types.empty_hits(r)
    assert hits.t.dtype == np.float32 and np.isinf(hits.t).all() and (hits.prim == -1).all()


def test_packets_keep_each_tile_together():
    from engine.packet.layout import packet_keys

    scene = load_named("whitted")
    rays, packets = primary_batch(scene, 40, 40, 16)
    for k in range(len(packets.offsets) - 1):
        pix = rays.pixel[packets.offsets[k]:packets.offsets[k + 1]]
        tiles, _ = packet_keys(pix[pix >= 0], 40, 16)
        assert len(set(tiles.tolist())) == 1
        # Each group of 4 lanes is one 2x2 screen block.
        quad = pix[:4]
        xs, ys = quad % 40, quad // 40
        assert xs.max() - xs.min() <= 1 and ys.max() - ys.min() <= 1


@pytest.mark.parametrize("n", [2, 4, 8, 16, 32])
def test_packet_order_is_the_documented_layout(n):
    """packet_order against a plain sort written from the module doc: tiles row by row, inside a
    tile its 2x2 blocks row by row, in a block the lanes (0,0), (1,0), (0,1), (1,1); rays sharing
    a pixel stay in input order; each packet padded to whole SIMD rays with -1."""
    from engine.packet.layout import packet_order

    width, height = 37, 29  # not multiples of any packet size
    rng = np.random.default_rng(n)
    pixel = rng.integers(0, width * height, 3000)  # with repeats

    def key(i):
        y, x = divmod(int(pixel[i]), width)
        tile = (y // n) * (-(-width // n)) + x // n
        block = ((y % n) // 2) * (n // 2) + (x % n) // 2
        return tile, block, (y % 2) * 2 + x % 2, i

    expected = sorted(range(len(pixel)), key=key)
    gather, packets = packet_order(pixel, width, height, n)
    offsets = packets.offsets
    assert (np.diff(offsets) % 4 == 0).all() and offsets[-1] == len(gather)
    assert gather[gather >= 0].tolist() == expected
    for k in range(len(offsets) - 1):
        lanes = gather[offsets[k]:offsets[k + 1]]
        live = lanes[lanes >= 0]
        assert (lanes[len(live):] == -1).all() and len(lanes) - len(live) < 4
        assert len({key(i)[0] for i in live}) == 1


def test_gather_batch_takes_candidates_and_pads_dead_lanes():
    """gather_batch against the array expressions it is defined by, on directions with zero and
    negative-zero components (their inverse is +-HUGE_INV's reciprocal, never inf)."""
    from engine.core.triangle import safe_inverse
    from engine.packet.layout import gather_batch

    rng = np.random.default_rng(11)
    m = 500
    org = rng.normal(size=(m, 3)).astype(np.float32)
    d = rng.normal(size=(m, 3)).astype(np.float32)
    d[::7, 0] = 0.0
    d[::11, 1] = -0.0
    tmin, tmax = rng.random(m).astype(np.float32), (rng.random(m) + 1).astype(np.float32)
    pixel, weight = rng.integers(0, 1000, m).astype(np.int32), rng.random((m, 3)).astype(np.float32)
    gather = rng.permutation(np.r_[np.arange(m), np.full(37, -1)])
    rays = gather_batch("shadow", gather, org, d, tmin, tmax, pixel, weight)
    live, take = gather >= 0, np.where(gather >= 0, gather, 0)
    want_dir = np.where(live[:, None], d[take], np.array([0, 0, 1], np.float32))
    assert rays.kind == "shadow"
    assert np.array_equal(rays.org, org[take])
    assert np.array_equal(rays.dir, want_dir) and np.array_equal(np.signbit(rays.dir), np.signbit(want_dir))
    assert np.array_equal(rays.inv_dir, safe_inverse(want_dir))
    assert np.array_equal(rays.tmin, np.where(live, tmin[take], 1)) and np.array_equal(rays.tmax, np.where(live, tmax[take], 0))
    assert np.array_equal(rays.pixel, np.where(live, pixel[take], -1))
    assert np.array_equal(rays.weight, np.where(live[:, None], weight[take], 0))
    assert all(a.flags.c_contiguous for a in rays[:7])
    empty = gather_batch("shadow", np.zeros(0, np.int64), org, d, tmin, tmax, pixel, weight)
    assert empty.org.shape == (0, 3) and empty.tmin.shape == (0,)

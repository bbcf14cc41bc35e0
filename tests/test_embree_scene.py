"""The Embree scene (engine.core.embree_scene) behind the ``embree`` traversal and the oracle:
its chunked, copy-free queries answer exactly what embreex answers on the same rays, whatever
the thread count; tmin moves the origin and is added back; dead lanes answer miss / not occluded
(embreex alone would call a negative segment occluded)."""
import numpy as np
import pytest

from engine.core import embree_scene
from engine.core.embree_scene import BALANCE_CHUNK, CHUNKS_PER_THREAD, MIN_CHUNK, EmbreeScene, chunk_bounds
from engine.core.triangle import safe_inverse
from engine.core.types import RayBatch, empty_hits
from engine.render.plugins import make_traversal
from scenes.catalog import load_named


@pytest.fixture(scope="module")
def whitted():
    return load_named("whitted")


def random_batch(tris, n, seed):
    """n incoherent rays around the scene, aimed at random triangles' centroids so most hit,
    with unbounded segments [0, inf)."""
    rng = np.random.default_rng(seed)
    corners = np.stack([tris.v0, tris.v1, tris.v2], axis=1)
    lo, hi = corners.reshape(-1, 3).min(0), corners.reshape(-1, 3).max(0)
    org = rng.uniform(lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo), size=(n, 3)).astype(np.float32)
    target = corners[rng.integers(0, tris.v0.shape[0], n)].mean(axis=1)
    d = (target - org + rng.normal(scale=0.05, size=(n, 3))).astype(np.float32)
    return RayBatch(org, d, safe_inverse(d), np.zeros(n, np.float32), np.full(n, np.inf, np.float32),
                    np.zeros(n, np.int32), np.ones((n, 3), np.float32), "reflection")


def bare(scene: EmbreeScene, org, d, tfar):
    """embreex's own answers, one call, no chunks: (t f32 with inf on a miss, prim i32, u, v, occluded bool)."""
    closest = scene.scene.run(np.ascontiguousarray(org, np.float32), np.ascontiguousarray(d, np.float32),
                              dists=np.array(tfar, np.float32), query="INTERSECT", output=1)
    occluded = np.asarray(scene.scene.run(np.ascontiguousarray(org, np.float32), np.ascontiguousarray(d, np.float32),
                                          dists=np.array(tfar, np.float32), query="OCCLUDED")) >= 0
    prim = closest["primID"].astype(np.int32)
    hit = prim >= 0
    return (np.where(hit, closest["tfar"], np.inf).astype(np.float32), np.where(hit, prim, -1),
            np.where(hit, closest["u"], 0).astype(np.float32), np.where(hit, closest["v"], 0).astype(np.float32),
            occluded)


def test_chunks_cover_the_batch_in_order():
    for n in (0, 1, MIN_CHUNK - 1, MIN_CHUNK * 3 + 5, 10 ** 6 + 3):
        for threads in (1, 2, 8):
            chunks = chunk_bounds(n, threads)
            assert (chunks == []) == (n == 0)
            assert [a for a, _ in chunks] == [0, *(b for _, b in chunks[:-1])][:len(chunks)]
            assert (chunks[-1][1] if chunks else 0) == n
            assert len(chunks) <= max(1, threads * CHUNKS_PER_THREAD)
            assert len(chunks) <= 1 or min(b - a for a, b in chunks) >= MIN_CHUNK
    assert len(chunk_bounds(10 ** 6, 2)) == 2 * CHUNKS_PER_THREAD  # big batches: balanced by a queue
    assert len(chunk_bounds(5 * MIN_CHUNK, 2)) == 2  # small ones: one call per worker
    assert len(chunk_bounds(2 * BALANCE_CHUNK * 2, 2)) == 4


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_chunked_queries_equal_one_embreex_call(whitted, threads):
    """Many chunks over a thread pool give embreex's own answers, ray for ray."""
    tris = whitted.triangles
    scene = EmbreeScene(tris, threads=threads)
    rays = random_batch(tris, 2 * threads * BALANCE_CHUNK + 17, seed=threads)
    assert len(chunk_bounds(rays.org.shape[0], threads)) == 2 * threads
    hits, occluded = scene.intersect(rays), scene.occluded(rays)
    t, prim, u, v, theirs = bare(scene, rays.org, rays.dir, np.full(rays.org.shape[0], 1e37))
    assert (prim >= 0).sum() > rays.org.shape[0] // 2  # plenty of hits
    np.testing.assert_array_equal(hits.prim, prim)
    np.testing.assert_array_equal(hits.t, t)
    np.testing.assert_array_equal(hits.u, u)
    np.testing.assert_array_equal(hits.v, v)
    np.testing.assert_array_equal(occluded, theirs)
    scene.close()


def test_segments_tmin_and_dead_lanes(whitted):
    """tmax cuts hits off; tmin > 0 moves the origin (only the chunks that need it) and comes
    back in t; dead lanes are misses and not occluded."""
    tris = whitted.triangles
    scene = EmbreeScene(tris, threads=2)
    rays = random_batch(tris, 3 * MIN_CHUNK, seed=7)
    n = rays.org.shape[0]
    full = scene.intersect(rays)
    hit = np.flatnonzero(full.prim >= 0)
    rng = np.random.default_rng(1)
    tmin, tmax = np.zeros(n, np.float32), np.full(n, np.inf, np.float32)
    # a third of the hits: segment ends just before the hit -> miss / not occluded
    short = hit[: len(hit) // 3]
    tmax[short] = full.t[short] * np.float32(0.999)
    # another third: dead lanes that would hit (tmax < tmin); one NaN segment
    dead = hit[len(hit) // 3: 2 * len(hit) // 3]
    tmin[dead], tmax[dead] = 1.0, 0.5
    tmax[dead[0]] = np.nan
    # the last chunk only: tmin > 0 on some rays (the other chunks keep the copy-free path)
    moved = np.arange(2 * MIN_CHUNK, n, 3)
    tmin[moved] = rng.uniform(0.01, 0.5, moved.size).astype(np.float32)
    tmax[moved] = np.maximum(tmax[moved], tmin[moved])
    batch = rays._replace(tmin=tmin, tmax=tmax)
    hits, occluded = scene.intersect(batch), scene.occluded(batch)

    assert (hits.prim[short] == -1).all() and np.isinf(hits.t[short]).all() and not occluded[short].any()
    assert (hits.prim[dead] == -1).all() and np.isinf(hits.t[dead]).all() and not occluded[dead].any()
    assert (hits.u[dead] == 0).all() and (hits.v[dead] == 0).all()
    # Every other ray: embreex's answer on the moved origin, with tmin added back.
    rest = np.setdiff1d(np.arange(n), np.concatenate([short, dead]))
    org = rays.org[rest] + tmin[rest, None] * rays.dir[rest]
    t, prim, u, v, theirs = bare(scene, org, rays.dir[rest], np.minimum(tmax[rest] - tmin[rest], 1e37))
    np.testing.assert_array_equal(hits.prim[rest], prim)
    np.testing.assert_array_equal(hits.t[rest], np.where(prim >= 0, t + tmin[rest], np.inf).astype(np.float32))
    np.testing.assert_array_equal(hits.u[rest], u)
    np.testing.assert_array_equal(occluded[rest], theirs)
    assert (hits.prim[np.intersect1d(rest, moved)] >= 0).sum() > 10  # the moved rays still hit things
    scene.close()


def test_whitted_loop_rays_take_the_copy_free_path(whitted, monkeypatch):
    """Every live ray a Whitted frame casts has tmin == 0: Embree as the traversal never moves an
    origin (never copies a ray), and its dead lanes answer miss / not occluded."""
    from engine.render.config import Config, with_overrides
    from engine.render.whitted import WhittedRenderer

    config = with_overrides(Config(), traversal=["embree"], frustum=["none"], size=(48, 32), depth=3)
    kinds, dead_answers = set(), []

    def observe(kind, query, rays, packets, answer):
        # Checked as the batch is handed over: the renderer reuses these arrays afterwards.
        kinds.add(kind)
        dead = ~(rays.tmin <= rays.tmax)
        dead_answers.append(int(np.count_nonzero(answer[dead] if query == "occluded" else answer.prim[dead] >= 0)))

    renderer = WhittedRenderer(whitted, config, observer=observe)
    renderer.tracer.prepare()  # Embree's scene built and warmed up before the spy goes in
    moved = []
    real = embree_scene.moved_origins
    monkeypatch.setattr(embree_scene, "moved_origins", lambda *args: moved.append(len(args[0])) or real(*args))
    renderer.render()
    assert kinds == {"primary", "shadow", "reflection", "refraction"}
    assert moved == []
    assert dead_answers and not any(dead_answers)


def test_plugin_writes_into_the_given_arrays_and_checks_their_length(whitted):
    tris = whitted.triangles
    rays = random_batch(tris, 100, seed=3)
    plugin = make_traversal("embree", {"robust": False})
    hits = empty_hits(100)
    hits.t[:] = -5.0  # stale values must be overwritten, misses included
    hits.prim[:] = 123
    plugin.intersect(None, tris, rays, None, None, hits, None)
    expected = plugin.scene_for(tris).intersect(rays)
    np.testing.assert_array_equal(hits.prim, expected.prim)
    np.testing.assert_array_equal(hits.t, expected.t)
    out = np.ones(100, np.bool_)
    plugin.occluded(None, tris, rays._replace(tmax=np.full(100, -1.0, np.float32)), None, None, out, None)
    assert not out.any()  # every lane dead
    with pytest.raises(ValueError):
        plugin.occluded(None, tris, rays, None, None, np.zeros(99, np.bool_), None)
    with pytest.raises(ValueError):
        plugin.intersect(None, tris, rays, None, None, empty_hits(99), None)

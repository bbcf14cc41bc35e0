"""``wide``: the mesh queries' 8-wide single-ray walk as a render traversal. Its hits equal
``single``'s (``tests/test_packet_traversals.py``); here: a whole frame audited against Embree,
and the 8-wide tree built once per BVH."""
from __future__ import annotations

import json

import numpy as np
import pytest

from engine.core.bvh import build_bvh
from engine.core.types import empty_hits, new_stats
from engine.packet.layout import make_batch
from engine.render.plugins import make_traversal
from scenes.catalog import load_named


def test_a_whitted_frame_by_wide_audits_clean_against_embree(tmp_path):
    from engine.cli import main

    report = tmp_path / "audit.json"
    assert main(["audit", "--size", "48x48", "--traversal", "wide", "--json", str(report)]) == 0
    data = json.loads(report.read_text())
    assert data["mismatches"] == [] and data["agreement"] == 1.0
    assert all(data["by_kind"][kind]["checked"] > 0 for kind in ("primary", "shadow", "reflection", "refraction"))


def test_the_tree_is_built_once_per_bvh_and_again_for_a_new_one():
    scene = load_named("whitted", {})
    tris = scene.triangles
    bvh = build_bvh(tris)
    wide = make_traversal("wide")
    first = wide.structure(bvh, tris)
    assert wide.structure(bvh, tris) is first
    rebuilt = build_bvh(tris, leaf_size=2)
    second = wide.structure(rebuilt, tris)
    assert second is not first and second[0].shape[0] != first[0].shape[0]
    # Each config makes its own instance: nothing built by one is seen by another.
    assert make_traversal("wide")._built is None


def test_wide_answers_every_ray_and_records_its_tree():
    """Dead rays (tmin > tmax) are misses without a reset by the tracer; stats get the tree."""
    scene = load_named("whitted", {})
    tris = scene.triangles
    bvh = build_bvh(tris)
    rng = np.random.default_rng(2)
    n = 300
    lo, hi = tris.v0.min(axis=0), tris.v0.max(axis=0)
    org = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    dirs = rng.normal(size=(n, 3)).astype(np.float32)
    tmin = np.zeros(n, np.float32)
    tmax = np.full(n, np.inf, np.float32)
    tmin[::3] = 2.0
    tmax[::3] = 1.0  # dead
    pixel = np.arange(n, dtype=np.int32)
    rays, packets = make_batch("reflection", org, dirs, tmin, tmax, pixel, np.ones((n, 3), np.float32), 30, 10, 2)
    hits = empty_hits(rays.org.shape[0])
    hits.t[:], hits.prim[:] = -5.0, 7  # garbage the traversal must overwrite
    stats = new_stats(1)
    wide = make_traversal("wide")
    wide.intersect(bvh, tris, rays, packets, None, hits, stats)
    reference = empty_hits(rays.org.shape[0])
    make_traversal("single").intersect(bvh, tris, rays, packets, None, reference, None)
    np.testing.assert_array_equal(hits.prim, reference.prim)
    np.testing.assert_array_equal(hits.t, reference.t)
    assert (hits.prim[rays.tmin > rays.tmax] == -1).all() and (hits.prim >= 0).any()
    occluded = np.ones(rays.org.shape[0], np.bool_)
    wide.occluded(bvh, tris, rays, packets, None, occluded, stats)
    np.testing.assert_array_equal(occluded, reference.prim >= 0)
    assert stats.extra["wide"]["nodes"] > 0 and stats.extra["wide"]["blocks"] > 0


@pytest.mark.parametrize("name", ["single", "wide", "embree", "rayspace"])
def test_a_traversal_that_ignores_frusta_is_not_charged_for_building_them(name):
    """The tracer builds frusta only for traversals that read them: a frustum builder configured
    beside ``single``, ``wide``, ``embree`` or ``rayspace`` is never called by ``trace``."""
    from engine.render.tracer import Tracer

    scene = load_named("whitted", {})
    tris = scene.triangles
    bvh = build_bvh(tris)
    n = 64
    rng = np.random.default_rng(4)
    org = np.tile(np.asarray(scene.camera.eye, np.float32), (n, 1))
    dirs = (tris.v0[rng.integers(0, len(tris.v0), n)] - org).astype(np.float32)
    rays, packets = make_batch("primary", org, dirs, np.zeros(n, np.float32), np.full(n, np.inf, np.float32),
                               np.arange(n, dtype=np.int32), np.ones((n, 3), np.float32), 8, 8, 4)

    class CountingFrustum:
        calls = 0

        def build(self, rays, packets, bounds):
            CountingFrustum.calls += 1
            raise AssertionError("built frusta for a traversal that does not read them")

    bounds = np.stack([bvh.bmin[0], bvh.bmax[0]]).astype(np.float32)
    tracer = Tracer(bvh, tris, bounds, {"primary": make_traversal(name)}, {"primary": CountingFrustum()})
    hits = tracer.trace("primary", "intersect", rays, packets)
    assert CountingFrustum.calls == 0 and (hits.prim >= 0).any()

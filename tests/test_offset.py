"""Secondary-ray origins leave their surface for real, so every traversal gives the shared
kernel's own answer on the Whitted loop's rays, even where coordinates are in the hundreds."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from engine.render import config as cfg
from engine.core.triangle import F32_INF, intersect_triangle, ray_shear
from engine.core.offset import coordinate_magnitude, hit_points, offset_origin
from engine.render.plugins import make_frustum, make_traversal
from engine.core.scene import make_triangles
from engine.core.types import copied_batch, empty_hits
from engine.render.whitted import WhittedRenderer

from brute_force import kernel_answer
from conftest import needs_shared_scenes

TRAVERSALS = ["single", "simd", "masked", "ranged", "partition", "auto", "rayspace"]
FRUSTUM = {"primary": "pinhole", "shadow": "pointlight", "reflection": "general", "refraction": "general"}


def big_floor(y=0.0):
    """Two triangles of the plane y = ``y``, x and z spanning -550 .. 550 (a Cornell-box floor)."""
    v = np.array([[-550, y, -550], [550, y, -550], [550, y, 550], [-550, y, 550]], np.float32)
    return make_triangles(v, np.array([[0, 2, 1], [0, 3, 2]]), 0)


@pytest.mark.parametrize("height", [0.0, 1e-3, 137.25])
def test_origins_leave_a_large_floor_on_the_requested_side(height):
    """Hits near zero on one axis of a triangle hundreds wide: the kernel must not find the
    triangle again from the offset origin, leaving either way (the old per-coordinate offset
    left these on the surface, where the kernel hit them at t = -0.0)."""
    tris = big_floor(height)
    rng = np.random.default_rng(3)
    n = 4000
    prim = rng.integers(0, 2, n).astype(np.int32)
    u = rng.uniform(0, 1, n).astype(np.float32)
    v = (rng.uniform(0, 1, n) * (1 - u)).astype(np.float32)
    p = hit_points(tris, prim, u, v)
    assert np.abs(p[:, 1].astype(np.float64) - np.float32(height)).max() <= np.spacing(np.float32(max(height, 1e-30)))
    magnitude = coordinate_magnitude(tris, prim, p)
    for side in (1.0, -1.0):
        normal = np.tile(np.float32([0, side, 0]), (n, 1))
        org = offset_origin(p, normal, magnitude)
        assert np.all((org[:, 1].astype(np.float64) - height) * side > 0)
        # Leave at every angle, grazing included: no hit on the floor at t >= 0.
        d = rng.normal(size=(n, 3)).astype(np.float32)
        d[:, 1] = np.abs(d[:, 1]) * side * rng.choice([1e-4, 1e-2, 1.0], n)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        for r in range(n):
            kx, ky, kz, sx, sy, sz = ray_shear(d[r, 0], d[r, 1], d[r, 2])
            o = org[r]
            for tri in range(2):
                t, _, _ = intersect_triangle(o[kx], o[ky], o[kz], kx, ky, kz, sx, sy, sz, np.float32(0),
                                             F32_INF, tris.v0, tris.v1, tris.v2, tri)
                assert t == F32_INF, (r, tri, t, o, d[r])


def test_hit_points_lie_on_the_triangle_plane():
    rng = np.random.default_rng(5)
    corners = rng.uniform(-300, 300, (50, 3, 3)).astype(np.float32)
    tris = make_triangles(corners.reshape(-1, 3), np.arange(150).reshape(-1, 3), 0)
    prim = np.repeat(np.arange(50, dtype=np.int32), 20)
    u = rng.uniform(0, 0.5, prim.size).astype(np.float32)
    v = rng.uniform(0, 0.5, prim.size).astype(np.float32)
    p = hit_points(tris, prim, u, v).astype(np.float64)
    n = np.cross(tris.v1[prim].astype(np.float64) - tris.v0[prim], tris.v2[prim].astype(np.float64) - tris.v0[prim])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    dist = np.abs(np.einsum("ij,ij->i", p - tris.v0[prim], n))
    ulp = np.spacing(np.abs(p).max(axis=1).astype(np.float32)).astype(np.float64)
    assert np.all(dist <= 2 * ulp)


def captured_batches(scene, config):
    """(renderer, [(kind, rays, packets)]) of one render, each batch copied as it is cast (the
    renderer reuses its per-lane arrays within a frame)."""
    batches = []
    renderer = WhittedRenderer(scene, config, observer=lambda kind, q, rays, packets, a: batches.append(
        (kind, *copied_batch(rays, packets))))
    renderer.render()
    return renderer, batches


@pytest.mark.parametrize("override", ["reflective", "refractive"])
def test_every_traversal_gives_the_kernels_answer_on_cornell_box_rays(override):
    """Cornell-box coordinates run to 556: before origins were offset by the triangle's
    magnitude, 13 shadow and 13 reflection rays at 256^2 depended on the order a traversal
    visited their triangles (the kernel hit the surface they left at t = -0.0)."""
    needs_shared_scenes()
    from scenes.catalog import scene_from_config

    config = cfg.with_overrides(cfg.Config(), scene="cornell-box", size=(256, 256), depth=3)
    config = cfg.validate(replace(config, override=override))
    scene = scene_from_config(config.scene, config.override)
    renderer, batches = captured_batches(scene, config)
    kinds = set()
    for kind, rays, packets in batches:
        kinds.add(kind)
        t, prim = kernel_answer(rays, renderer.tris)
        live = rays.tmin <= rays.tmax
        for name in TRAVERSALS:
            frusta = ["none"] if name in ("single", "rayspace") else ["none", FRUSTUM[kind]]
            for frustum in frusta:
                traversal = make_traversal(name)
                built = make_frustum(frustum).build(rays, packets, renderer.bounds)
                hits = empty_hits(rays.org.shape[0])
                traversal.intersect(renderer.bvh, renderer.tris, rays, packets, built, hits, None)
                occluded = np.zeros(rays.org.shape[0], np.bool_)
                traversal.occluded(renderer.bvh, renderer.tris, rays, packets, built, occluded, None)
                what = f"{kind} rays, {name} with frustum {frustum}"
                np.testing.assert_array_equal(hits.prim[live], prim[live], err_msg=what)
                np.testing.assert_array_equal(hits.t[live], t[live], err_msg=what)
                np.testing.assert_array_equal(occluded[live], prim[live] >= 0, err_msg=what)
    assert kinds == {"primary", "shadow", "reflection"} | ({"refraction"} if override == "refractive" else set())

"""The rays of the GPU benchmark: a scene's camera rays and rays spawned at their hits.

The same sets the issue's Mitsuba table was measured on: closest-hit camera rays; any-hit
shadow rays from every hit to the first light and to every light; closest-hit mirror
reflections; closest-hit cosine-distributed bounces (incoherent). Secondary rays leave from the
hit point offset along the ray-facing normal exactly as the renderer offsets them
(``engine.core.offset``), found by Embree on the camera rays.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.core.offset import coordinate_magnitude, hit_points, offset_origin
from engine.core.triangle import safe_inverse
from engine.core.types import RayBatch
from engine.render.camera import camera_rays
from engine.render.direct_light import SHADOW_TMAX_SCALE

#: name -> query, in the order the tables list them.
RAY_SETS = {"primary": "closest", "shadow-light0": "occluded", "shadow-all": "occluded", "mirror": "closest",
            "bounce": "closest"}


@dataclass
class RaySet:
    """R rays on the host: org, dir f32[R,3], tmin, tmax f32[R], pixel i32[R] (ancestral pixel on
    the ``screen`` = (width, height)), and ``batch``, the same as a RayBatch for the oracles."""

    org: np.ndarray
    dir: np.ndarray
    tmin: np.ndarray
    tmax: np.ndarray
    pixel: np.ndarray
    screen: tuple
    batch: RayBatch


def _ray_set(kind, org, dirs, tmax, pixel, screen) -> RaySet:
    org = np.ascontiguousarray(org, np.float32)
    dirs = np.ascontiguousarray(dirs, np.float32)
    tmin = np.zeros(org.shape[0], np.float32)
    tmax = np.ascontiguousarray(tmax, np.float32)
    pixel = np.ascontiguousarray(pixel, np.int32)
    batch = RayBatch(org, dirs, safe_inverse(dirs), tmin, tmax, pixel, np.ones_like(org), kind)
    return RaySet(org, dirs, tmin, tmax, pixel, screen, batch)


def _cosine_directions(normal: np.ndarray, rng) -> np.ndarray:
    """Cosine-distributed unit directions about unit normals f32[M,3] -> f32[M,3]."""
    m = normal.shape[0]
    u1, u2 = rng.random(m), rng.random(m)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], axis=1)
    n = normal.astype(np.float64)
    helper = np.where(np.abs(n[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(helper, n)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(n, t)
    d = local[:, :1] * t + local[:, 1:2] * b + local[:, 2:] * n
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def ray_sets(scene, bvh, width: int, height: int, wanted, seed: int = 7) -> dict:
    """{name: (query "closest" | "occluded", RaySet)} of the ``wanted`` sets (keys of RAY_SETS)
    for ``scene`` seen at width x height. ``bvh``: unused (Embree finds the camera hits)."""
    from validation.audit import make_oracle

    screen = (width, height)
    org, dirs = camera_rays(scene, width, height)
    pixels = np.arange(width * height, dtype=np.int32)
    primary = _ray_set("primary", org, dirs, np.full(width * height, np.inf, np.float32), pixels, screen)
    out = {}
    if "primary" in wanted:
        out["primary"] = ("closest", primary)
    if set(wanted) <= {"primary"}:
        return out
    tris = scene.triangles
    hits = make_oracle("embree", tris).intersect(primary.batch)
    hit = hits.prim >= 0
    prim, pixel = hits.prim[hit], pixels[hit]
    points = hit_points(tris, prim, hits.u[hit], hits.v[hit])
    view = dirs[hit]
    ng = tris.ng[prim]
    facing = np.where((np.einsum("ij,ij->i", ng, view) < 0)[:, None], ng, -ng).astype(np.float32)
    leave = offset_origin(points, facing, coordinate_magnitude(tris, prim, points))
    lights = [np.asarray(l.position, np.float32) for l in scene.lights]
    for name in wanted:
        if name.startswith("shadow") and lights:
            chosen = lights[:1] if name == "shadow-light0" else lights
            parts = []
            for light in chosen:
                to = light[None, :] - leave
                dist = np.linalg.norm(to, axis=1).astype(np.float32)
                parts.append((leave, to / np.maximum(dist, 1e-30)[:, None], dist * SHADOW_TMAX_SCALE, pixel))
            out[name] = ("occluded", _ray_set("shadow", *(np.concatenate(c) for c in zip(*parts)), screen))
        elif name == "mirror":
            d = view - 2 * np.einsum("ij,ij->i", view, facing)[:, None] * facing
            out[name] = ("closest", _ray_set("reflection", leave, d, np.full(len(d), np.inf), pixel, screen))
        elif name == "bounce":
            d = _cosine_directions(facing, np.random.default_rng(seed))
            out[name] = ("closest", _ray_set("reflection", leave, d, np.full(len(d), np.inf), pixel, screen))
    return out

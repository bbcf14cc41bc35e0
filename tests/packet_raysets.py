"""Ray sets for the packet-traversal tests, named by coherence: primary, shadow, reflection
and refraction rays on a real scene, all ordered into n x n packets by ancestral pixel.

Secondary rays are built from the reference traversal's primary hits (reflected about or bent
through the geometric normal, origins offset off the surface), so every packet size sees the
same candidate rays, only grouped differently.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.core.bvh import build_bvh
from engine.core.offset import coordinate_magnitude, hit_points, offset_origin
from engine.packet.layout import make_batch
from engine.render.plugins import make_traversal
from engine.core.types import empty_hits
from engine.render.camera import camera_rays

#: Index of refraction of the refraction-like rays.
IOR = np.float32(1.5)


@dataclass
class Candidates:
    """Unordered rays of one kind: org, dir f32[M,3]; tmin, tmax f32[M]; pixel i32[M]."""

    kind: str
    org: np.ndarray
    dir: np.ndarray
    tmin: np.ndarray
    tmax: np.ndarray
    pixel: np.ndarray

    def batch(self, width: int, height: int, n: int):
        """(RayBatch, Packets) in n x n packet order."""
        return make_batch(self.kind, self.org, self.dir, self.tmin, self.tmax, self.pixel,
                          np.ones((len(self.pixel), 3), np.float32), width, height, n)


@dataclass
class SceneRays:
    """A scene's BVH and triangles with its candidate rays by kind."""

    name: str
    bvh: object
    tris: object
    bounds: np.ndarray
    width: int
    height: int
    rays: dict


def scene_rays(scene, width: int, height: int) -> SceneRays:
    """Primary rays through every pixel and the shadow / reflection / refraction rays spawned at
    their closest hits (by ``single``)."""
    tris = scene.triangles
    bvh = build_bvh(tris)
    bounds = np.stack([bvh.bmin[0], bvh.bmax[0]]).astype(np.float32)
    org, d = camera_rays(scene, width, height)
    count = width * height
    pixel = np.arange(count, dtype=np.int32)
    primary = Candidates("primary", org, d, np.zeros(count, np.float32), np.full(count, np.inf, np.float32),
                         pixel)
    rays, packets = primary.batch(width, height, 8)
    hits = empty_hits(rays.org.shape[0])
    make_traversal("single").intersect(bvh, tris, rays, packets, None, hits, None)
    idx = np.flatnonzero(hits.prim >= 0)
    prim = hits.prim[idx]
    # Origins as the Whitted loop makes them (engine.core.offset).
    p = hit_points(tris, prim, hits.u[idx], hits.v[idx])
    magnitude = coordinate_magnitude(tris, prim, p)
    d = rays.dir[idx]
    ng = tris.ng[prim]
    cos = np.einsum("ij,ij->i", ng, d)
    facing = np.where((cos < 0)[:, None], ng, -ng)  # geometric normal on the incoming side
    front = offset_origin(p, facing, magnitude)
    back = offset_origin(p, -facing, magnitude)
    hit_pixel = rays.pixel[idx]
    m = len(idx)

    light = np.asarray(scene.lights[0].position, np.float32)
    to_light = light - front
    dist = np.linalg.norm(to_light, axis=1).astype(np.float32)
    shadow = Candidates("shadow", front, (to_light / dist[:, None]).astype(np.float32),
                        np.zeros(m, np.float32), dist, hit_pixel)

    cos_i = np.abs(cos)[:, None]
    reflected = (d + 2 * cos_i * facing).astype(np.float32)
    reflection = Candidates("reflection", front, reflected, np.zeros(m, np.float32),
                            np.full(m, np.inf, np.float32), hit_pixel)

    eta = np.where(cos < 0, 1 / IOR, IOR).astype(np.float32)[:, None]
    k = 1 - eta * eta * (1 - cos_i * cos_i)
    bent = eta * d + (eta * cos_i - np.sqrt(np.maximum(k, 0))) * facing
    through = k[:, 0] >= 0  # total internal reflection spawns no refraction ray
    refraction = Candidates("refraction", back[through], bent[through].astype(np.float32),
                            np.zeros(int(through.sum()), np.float32),
                            np.full(int(through.sum()), np.inf, np.float32), hit_pixel[through])
    return SceneRays(scene.name, bvh, tris, bounds, width, height,
                     {"primary": primary, "shadow": shadow, "reflection": reflection,
                      "refraction": refraction})

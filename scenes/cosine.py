"""A mirror surface z = cos(n x) cos(n y) standing in a room: many incoherent reflection rays.

The surface spans x, y in [-pi, pi] (n periods across each side) as a (resolution x resolution)
grid of quads (2 resolution^2 triangles) with analytic per-vertex normals. It is scaled uniformly
(so the shape is exactly the formula), rests on the floor and is a near-perfect mirror. The
room is the BART kitchen when its files are on the scene search path (``bart-kitchen``, at
``time``), else the procedural ``erw6`` room; ``scene.info["host"]`` says which. The camera looks
down at the surface; the host's lights stay.

Parameters: ``n`` (frequency, > 0, default 4), ``resolution`` (quads per side, default 128).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from engine.core.errors import ConfigError
from engine.core.scene import Camera, Material, concat_triangles, make_triangles

from .catalog import entries, find_files, load_named, scene_loader
from .erw6 import erw6_scene

#: Where the surface goes in each host: centre of its footprint on the floor, footprint side,
#: and the camera (eye, look_at, vertical fov).
PLACEMENT = {
    "bart-kitchen": {"centre": (2.3, 0.0, 2.75), "side": 1.2,
                     "camera": ((3.6, 1.1, 3.25), (2.2, 0.1, 2.6), 55.0)},
    "erw6": {"centre": (2.0, 0.0, 3.1), "side": 1.2,
             "camera": ((3.7, 1.6, 3.9), (1.9, 0.2, 2.7), 55.0)},
}

MIRROR = Material("cosine-mirror", ambient=(0.0, 0.0, 0.0), diffuse=(0.05, 0.05, 0.05),
                  specular=(0.6, 0.6, 0.6), shininess=80.0, reflectance=(0.9, 0.9, 0.9))


def cosine_surface(n: float, resolution: int):
    """z = cos(n x) cos(n y) over [-pi, pi]^2, in its own coordinates (z up):
    (vertices f64[(r+1)^2, 3], faces i64[2 r^2, 3], normals f64[(r+1)^2, 3]), r = resolution,
    wound so that the normals point towards +z."""
    s = np.linspace(-math.pi, math.pi, resolution + 1)
    x, y = np.meshgrid(s, s, indexing="ij")
    z = np.cos(n * x) * np.cos(n * y)
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    # Normal = (-dz/dx, -dz/dy, 1), normalised.
    normals = np.stack([n * np.sin(n * x) * np.cos(n * y), n * np.cos(n * x) * np.sin(n * y),
                        np.ones_like(z)], axis=-1).reshape(-1, 3)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    i, j = np.meshgrid(np.arange(resolution), np.arange(resolution), indexing="ij")
    k = (i * (resolution + 1) + j).ravel()
    r1 = resolution + 1
    faces = np.concatenate([np.stack([k, k + r1, k + r1 + 1], 1), np.stack([k, k + r1 + 1, k + 1], 1)])
    return vertices, faces, normals


def place(vertices: np.ndarray, normals: np.ndarray, centre, side: float):
    """Surface coordinates (z up) to the room's (y up): uniform scale side / 2 pi, resting on the
    floor at ``centre``. Returns (vertices f64[V,3], normals f64[V,3])."""
    scale = side / (2 * math.pi)
    cx, cy, cz = centre
    lifted = vertices[:, 2] - vertices[:, 2].min()
    # (x, y, z) -> (x, z, -y) keeps the handedness: a rotation of -90 degrees about x.
    world = np.stack([cx + scale * vertices[:, 0], cy + 0.002 + scale * lifted, cz - scale * vertices[:, 1]], 1)
    world_normals = np.stack([normals[:, 0], normals[:, 2], -normals[:, 1]], 1)
    return world, world_normals


def _kitchen_available() -> bool:
    entry = entries().get("bart-kitchen")
    return entry is not None and not find_files(entry)[1]


@scene_loader("cosine-n")
def cosine_scene(files, params, time):
    n = params.get("n", 4)
    if isinstance(n, bool) or not isinstance(n, (int, float)) or not 0 < n <= 1000:
        raise ConfigError(f"cosine-n: n must be a number in (0, 1000], got {n!r}")
    resolution = params.get("resolution", 128)
    if isinstance(resolution, bool) or not isinstance(resolution, int) or not 1 <= resolution <= 4096:
        raise ConfigError(f"cosine-n: resolution must be an integer in 1..4096, got {resolution!r}")
    if _kitchen_available():
        host, room = "bart-kitchen", load_named("bart-kitchen", time=time)
    else:
        host, room = "erw6", erw6_scene([], {}, time)
    where = PLACEMENT[host]
    vertices, faces, normals = cosine_surface(float(n), resolution)
    vertices, normals = place(vertices, normals, where["centre"], where["side"])
    surface = make_triangles(vertices, faces, len(room.materials), normals=normals, source="cosine-n")
    triangles = concat_triangles([room.triangles, surface])
    eye, look_at, fov = where["camera"]
    info = {"host": host, "n": n, "resolution": resolution, "surface_triangles": int(len(faces)),
            "host_triangles": room.n_triangles, "triangles": int(triangles.v0.shape[0])}
    return replace(room, name="cosine-n", triangles=triangles, materials=room.materials + [MIRROR],
                   camera=Camera(eye, look_at, (0.0, 1.0, 0.0), fov), source=f"procedural in {host}",
                   info=info)

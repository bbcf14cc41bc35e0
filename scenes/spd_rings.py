"""Eric Haines' SPD "rings" (Standard Procedural Databases): a pyramid of ring units in front of
a white backdrop, three point lights. Procedural: needs no data files.

A unit is six pentagonal rings of cylinders (radius r = 0.07412) with a sphere at every vertex.
Its 30 vertices are the edge midpoints of a dodecahedron: pentagon 0 lies in the XY plane with a
vertex on +X, pentagons 1-5 are pentagon 0 rotated about X by 2 acos(cos 60 / sin 36) (the
angle between adjacent dodecahedron faces) and then about Z by (2p - 1) * 36 degrees; the unit is
scaled by 1 / (1 + r) to fit a unit sphere. Layer d (0 .. size_factor - 1) is a (d+1) x (d+1)
grid of units 2 apart in X and Z at Y = (d + 1) / sin 22.5; the camera looks up +Y at the apex.
Each ring has its own colour (red, green, blue, cyan, magenta, yellow), diffuse 0.5, highlight
0.3 (Phong 37) and mirror reflectance 0.2; the backdrop is white and diffuse.

Tessellation (R = ``tessellation``): a cylinder is an open tube of 4R sides (8R triangles), a
sphere a subdivided cube (12 R^2 triangles). Units: SF (SF + 1) (2 SF + 1) / 6; triangles:
units * 30 * (8 R + 12 R^2) + 2 (the backdrop). size_factor 7 (SPD's default) and R = 3 give
140 units, 8,400 primitives and 554,402 triangles.

Parameters: ``size_factor`` (layers, default 7), ``tessellation`` (default 3).
"""
from __future__ import annotations

import math

import numpy as np

from engine.core.errors import ConfigError
from engine.core.scene import Camera, Material, PointLight, SceneBuilder

from .aff import axis_angle_matrix, cone_triangles, sphere_triangles
from .catalog import scene_loader

RADIUS = 0.07412
RING_COLOURS = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0),
                (0.0, 1.0, 1.0), (1.0, 0.0, 1.0), (1.0, 1.0, 0.0))


def unit_vertices(radius: float = RADIUS) -> np.ndarray:
    """f64[30,3]: the six pentagons' vertices, pentagon p at rows 5p .. 5p+4."""
    scale = 1.0 / (1.0 + radius)
    angles = np.arange(5) * (2 * math.pi / 5)
    pentagon = scale * np.stack([np.cos(angles), np.sin(angles), np.zeros(5)], axis=1)
    tilt = math.degrees(2 * math.acos(math.cos(math.pi / 3) / math.sin(math.pi / 5)))
    rings = [pentagon]
    for p in range(1, 6):
        rotation = axis_angle_matrix((0, 0, 1), (2 * p - 1) * 36.0) @ axis_angle_matrix((1, 0, 0), tilt)
        rings.append(pentagon @ rotation.T)
    return np.concatenate(rings)


def unit_triangles(tessellation: int, radius: float = RADIUS):
    """One unit at the origin: (corners f64[T,3,3], normals f64[T,3,3], ring i32[T]) with
    T = 30 (8R + 12R^2); ``ring`` (0..5) picks the colour."""
    vertices = unit_vertices(radius)
    corners, normals, ring = [], [], []
    for element in range(30):
        previous = element + 4 if element % 5 == 0 else element - 1
        for c, n in (cone_triangles(vertices[element], radius, vertices[previous], radius, tessellation),
                     sphere_triangles(vertices[element], radius, tessellation)):
            corners.append(c)
            normals.append(n)
            ring.append(np.full(len(c), element // 5, np.int32))
    return np.concatenate(corners), np.concatenate(normals), np.concatenate(ring)


def unit_offsets(size_factor: int) -> np.ndarray:
    """f64[U,3]: unit centres, layer by layer (U = SF (SF + 1) (2 SF + 1) / 6)."""
    spread = 1.0 / math.sin(math.pi / 8)
    offsets = []
    for depth in range(size_factor):
        for z in range(depth + 1):
            for x in range(depth + 1):
                offsets.append((2 * x - depth, spread * (depth + 1), 2 * z - depth))
    return np.array(offsets, np.float64).reshape(-1, 3)


def _positive_int(params: dict, key: str, default: int, high: int) -> int:
    value = params.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= high:
        raise ConfigError(f"spd-rings: {key} must be an integer in 1..{high}, got {value!r}")
    return value


@scene_loader("spd-rings")
def rings_scene(files, params, time):
    size_factor = _positive_int(params, "size_factor", 7, 20)
    tessellation = _positive_int(params, "tessellation", 3, 16)
    spread = 1.0 / math.sin(math.pi / 8)
    b = SceneBuilder("spd-rings")
    wall = b.add_material(Material("backdrop", ambient=(0.0, 0.0, 0.0), diffuse=(1.0, 1.0, 1.0),
                                   specular=(0.0, 0.0, 0.0), shininess=1.0))
    rings = [b.add_material(Material(f"ring-{k}", ambient=(0.0, 0.0, 0.0),
                                     diffuse=tuple(0.5 * c for c in colour), specular=(0.3, 0.3, 0.3),
                                     shininess=37.0, reflectance=(0.2, 0.2, 0.2)))
             for k, colour in enumerate(RING_COLOURS)]

    eye = np.array([-1.0, -spread, 0.5])
    # The backdrop just spans the 45 degree view (+1%) behind the last layer.
    wall_y = spread * (size_factor + 1)
    half = 1.01 * (wall_y - eye[1]) * math.tan(math.pi / 8)
    quad = np.array([[eye[0] + sx * half, wall_y, eye[2] + sz * half]
                     for sx, sz in ((1, 1), (-1, 1), (-1, -1), (1, -1))])
    b.add_mesh(quad, [[0, 1, 2], [0, 2, 3]], wall)

    corners, normals, ring = unit_triangles(tessellation)
    offsets = unit_offsets(size_factor)
    placed = (corners[None] + offsets[:, None, None, :]).reshape(-1, 3, 3)      # [U*T, 3, 3]
    n_units, per_unit = len(offsets), len(corners)
    t = n_units * per_unit
    b.add_mesh(placed.reshape(-1, 3), np.arange(3 * t).reshape(t, 3),
               np.tile(np.asarray(rings, np.int32)[ring], n_units),
               normals=np.broadcast_to(normals, (n_units,) + normals.shape).reshape(-1, 3, 3))

    brightness = 1.0 / math.sqrt(3.0)   # SPD scales three lights for renderers that do not
    lights = [PointLight((x, -spread, z), (brightness,) * 3) for x, z in ((3.0, 3.0), (-4.0, 1.0), (2.0, -4.0))]
    camera = Camera(tuple(eye), (eye[0], eye[1] + 1.0, eye[2]), (0.0, 0.0, 1.0), 45.0)
    info = {"size_factor": size_factor, "tessellation": tessellation, "units": n_units,
            "cylinders": 30 * n_units, "spheres": 30 * n_units,
            "triangles_per_cylinder": 8 * tessellation, "triangles_per_sphere": 12 * tessellation ** 2,
            "triangles": t + 2}
    return b.build(camera=camera, lights=lights, background=(0.078, 0.361, 0.753),
                   ambient_light=(1.0, 1.0, 1.0), info=info)

"""A stand-in for the ERW6 test scene (a plain room with a few boxes and one light, ~800
triangles), which is not available here. Procedural: needs no data files.

The room is 4 x 2.6 x 4 (x, y up, z) with inward-facing walls, floor and ceiling, each a grid of
``subdivisions`` x ``subdivisions`` quads; three boxes stand on the floor (a low table block, a
tall cabinet, a small crate). One white point light hangs under the ceiling. Triangles:
12 s^2 + 36 (804 at the default s = 8, ERW6's count).

Parameters: ``subdivisions`` (quads per wall side, default 8).
"""
from __future__ import annotations

import numpy as np

from engine.core.errors import ConfigError
from engine.core.scene import Camera, Material, PointLight, SceneBuilder

from .catalog import scene_loader

ROOM = np.array([4.0, 2.6, 4.0])

#: (lower corner, upper corner, material name) of the boxes on the floor.
BOXES = (((1.3, 0.0, 1.5), (2.7, 0.75, 2.4), "table"),
         ((0.2, 0.0, 0.2), (0.8, 1.7, 0.75), "cabinet"),
         ((2.9, 0.0, 2.9), (3.4, 0.45, 3.4), "crate"))


def grid_quad(origin, u, v, subdivisions: int):
    """A planar s x s grid spanning origin + a u + b v (a, b in [0, 1]):
    (vertices f64[(s+1)^2, 3], faces i64[2 s^2, 3]), wound counter-clockwise around u x v."""
    s = subdivisions
    a, b = np.meshgrid(np.linspace(0, 1, s + 1), np.linspace(0, 1, s + 1), indexing="ij")
    vertices = np.asarray(origin, float) + a.reshape(-1, 1) * np.asarray(u, float) + \
        b.reshape(-1, 1) * np.asarray(v, float)
    i, j = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
    k = (i * (s + 1) + j).ravel()
    faces = np.concatenate([np.stack([k, k + s + 1, k + s + 2], 1), np.stack([k, k + s + 2, k + 1], 1)])
    return vertices, faces


def box(lower, upper):
    """An axis-aligned box facing outwards: (vertices f64[8,3], faces i64[12,3])."""
    (x0, y0, z0), (x1, y1, z1) = lower, upper
    vertices = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)], float)
    # Corner index = 4 * (x is x1) + 2 * (y is y1) + (z is z1).
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))]
    return vertices, np.array(faces)


def build_room(builder: SceneBuilder, subdivisions: int) -> None:
    """Add the room's six inward-facing sides and the boxes to ``builder``."""
    w, h, d = ROOM
    wall = builder.add_material(Material("wall", ambient=(0.12, 0.12, 0.12), diffuse=(0.75, 0.75, 0.72)))
    floor = builder.add_material(Material("floor", ambient=(0.1, 0.08, 0.06), diffuse=(0.6, 0.45, 0.3),
                                          specular=(0.2, 0.2, 0.2), shininess=30.0))
    ceiling = builder.add_material(Material("ceiling", ambient=(0.15, 0.15, 0.15), diffuse=(0.9, 0.9, 0.9)))
    accent = builder.add_material(Material("accent-wall", ambient=(0.08, 0.1, 0.12),
                                           diffuse=(0.45, 0.6, 0.75)))
    # (origin, u, v) with u x v pointing into the room.
    sides = (((0, 0, 0), (0, 0, d), (w, 0, 0), floor),
             ((0, h, 0), (w, 0, 0), (0, 0, d), ceiling),
             ((0, 0, 0), (w, 0, 0), (0, h, 0), accent),      # z = 0, facing +z
             ((0, 0, d), (0, h, 0), (w, 0, 0), wall),        # z = d, facing -z
             ((0, 0, 0), (0, h, 0), (0, 0, d), wall),        # x = 0, facing +x
             ((w, 0, 0), (0, 0, d), (0, h, 0), wall))        # x = w, facing -x
    for origin, u, v, material in sides:
        vertices, faces = grid_quad(origin, u, v, subdivisions)
        builder.add_mesh(vertices, faces, material)
    colours = {"table": (0.7, 0.35, 0.2), "cabinet": (0.3, 0.45, 0.7), "crate": (0.75, 0.7, 0.3)}
    for lower, upper, name in BOXES:
        material = builder.add_material(Material(name, ambient=tuple(0.1 * c for c in colours[name]),
                                                 diffuse=colours[name], specular=(0.25, 0.25, 0.25),
                                                 shininess=40.0))
        vertices, faces = box(lower, upper)
        builder.add_mesh(vertices, faces, material)


def room_light() -> PointLight:
    return PointLight((2.0, 2.45, 2.0), (1.0, 1.0, 1.0))


@scene_loader("erw6")
def erw6_scene(files, params, time):
    subdivisions = params.get("subdivisions", 8)
    if isinstance(subdivisions, bool) or not isinstance(subdivisions, int) or not 1 <= subdivisions <= 256:
        raise ConfigError(f"erw6: subdivisions must be an integer in 1..256, got {subdivisions!r}")
    builder = SceneBuilder("erw6")
    build_room(builder, subdivisions)
    camera = Camera(eye=(3.7, 1.7, 3.8), look_at=(1.6, 0.6, 1.4), up=(0.0, 1.0, 0.0), fov=60.0)
    info = {"subdivisions": subdivisions, "triangles": 12 * subdivisions ** 2 + 12 * len(BOXES)}
    return builder.build(camera=camera, lights=[room_light()], background=(0.0, 0.0, 0.0),
                         ambient_light=(1.0, 1.0, 1.0), info=info)

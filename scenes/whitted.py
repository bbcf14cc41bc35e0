"""The built-in default scene, after Whitted (1980): a checkerboard floor, a mirror sphere,
a glass sphere and one point light. Procedural: needs no data files.

Parameters: ``checks`` (squares per floor side, default 16), ``subdivisions`` (icosphere
level of the spheres, default 3: 1,280 triangles each).
"""
from __future__ import annotations

import numpy as np

from engine.core.scene import Camera, Material, PointLight, SceneBuilder

from .catalog import scene_loader


def checkerboard(builder: SceneBuilder, size: float, checks: int, y: float, dark: int, light: int) -> None:
    """A square floor of ``checks`` x ``checks`` quads in the plane y, alternating materials."""
    step = size / checks
    for i in range(checks):
        for j in range(checks):
            x0, z0 = -size / 2 + i * step, -size / 2 + j * step
            quad = np.array([[x0, y, z0], [x0, y, z0 + step], [x0 + step, y, z0 + step], [x0 + step, y, z0]])
            builder.add_mesh(quad, [[0, 1, 2], [0, 2, 3]], dark if (i + j) % 2 else light)


#: The twelve corners of an icosahedron, (0, +-1, +-phi) and its cyclic permutations, and its
#: twenty faces, each counter-clockwise seen from outside.
_PHI = (1.0 + 5.0 ** 0.5) / 2.0
ICOSAHEDRON_CORNERS = ((-1.0, _PHI, 0.0), (1.0, _PHI, 0.0), (-1.0, -_PHI, 0.0), (1.0, -_PHI, 0.0),
                       (0.0, -1.0, _PHI), (0.0, 1.0, _PHI), (0.0, -1.0, -_PHI), (0.0, 1.0, -_PHI),
                       (_PHI, 0.0, -1.0), (_PHI, 0.0, 1.0), (-_PHI, 0.0, -1.0), (-_PHI, 0.0, 1.0))
ICOSAHEDRON_FACES = ((0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
                     (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
                     (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1))


def icosphere(subdivisions: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices f64[V,3], faces i64[F,3]) of a sphere of ``radius`` about the origin: an
    icosahedron whose faces are split in four ``subdivisions`` times, every new corner pushed out
    to the sphere (V = 10 * 4^s + 2, F = 20 * 4^s; faces counter-clockwise from outside). Made
    here rather than by trimesh, whose import (scipy with it) took 0.66 s of the 2.7 s a render of
    this scene took from start to finish."""
    corners = [np.asarray(c) / np.linalg.norm(c) for c in ICOSAHEDRON_CORNERS]
    faces = list(ICOSAHEDRON_FACES)
    for _ in range(subdivisions):
        middle = {}  # edge (low, high corner) -> its midpoint's corner

        def midpoint(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in middle:
                point = corners[a] + corners[b]
                corners.append(point / np.linalg.norm(point))
                middle[key] = len(corners) - 1
            return middle[key]

        split = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            split += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = split
    return np.array(corners) * radius, np.array(faces, np.int64)


def sphere(builder: SceneBuilder, centre, radius: float, material: int, subdivisions: int) -> None:
    """An icosphere with smooth per-vertex normals."""
    vertices, faces = icosphere(subdivisions, radius)
    builder.add_mesh(vertices + np.asarray(centre), faces, material,
                     normals=vertices / np.linalg.norm(vertices, axis=1, keepdims=True))


@scene_loader("whitted")
def whitted_scene(files, params, time):
    checks = int(params.get("checks", 16))
    subdivisions = int(params.get("subdivisions", 3))
    b = SceneBuilder("whitted")
    red = b.add_material(Material("check-red", ambient=(0.1, 0.02, 0.02), diffuse=(0.8, 0.15, 0.1),
                                  specular=(0.1, 0.1, 0.1), shininess=20))
    yellow = b.add_material(Material("check-yellow", ambient=(0.1, 0.1, 0.02), diffuse=(0.9, 0.85, 0.2),
                                     specular=(0.1, 0.1, 0.1), shininess=20))
    mirror = b.add_material(Material("mirror", ambient=(0.0, 0.0, 0.0), diffuse=(0.05, 0.05, 0.05),
                                     specular=(0.6, 0.6, 0.6), shininess=80, reflectance=(0.85, 0.85, 0.85)))
    glass = b.add_material(Material("glass", ambient=(0.0, 0.0, 0.0), diffuse=(0.0, 0.0, 0.0),
                                    specular=(0.7, 0.7, 0.7), shininess=120, reflectance=(0.08, 0.08, 0.08),
                                    transmission=0.9, ior=1.5))
    checkerboard(b, 12.0, checks, 0.0, red, yellow)
    sphere(b, (-1.1, 1.0, -1.2), 1.0, mirror, subdivisions)
    sphere(b, (1.0, 1.0, 0.6), 1.0, glass, subdivisions)
    camera = Camera(eye=(0.0, 2.6, 7.5), look_at=(0.0, 0.9, 0.0), up=(0.0, 1.0, 0.0), fov=42.0)
    light = PointLight((4.0, 8.0, 5.0), (1.0, 1.0, 1.0))
    return b.build(camera=camera, lights=[light], background=(0.25, 0.45, 0.8), ambient_light=(1.0, 1.0, 1.0))

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


def sphere(builder: SceneBuilder, centre, radius: float, material: int, subdivisions: int) -> None:
    """An icosphere with smooth per-vertex normals."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    builder.add_mesh(mesh.vertices + np.asarray(centre), mesh.faces, material,
                     normals=mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True))


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

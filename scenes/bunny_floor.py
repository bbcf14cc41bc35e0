"""The Stanford Bunny on a mirror floor: the first paper's third Table 2 scene (Overbeck et al.
2008), whose reflection rays off the floor all see the bunny.

The bunny (PLY, one of its four levels of detail) keeps its plain diffuse material; under it a
square floor ``floor_size`` bunny heights on a side, a ``subdivisions`` x ``subdivisions`` grid of
quads, with mirror reflectance 0.6 over a grey diffuse layer. The camera looks down at the bunny
from the front so the floor fills the lower half of the image; one white point light above.

Parameters: ``lod`` (0..3, picks the PLY file as in ``bunny``), ``floor_size`` (default 6),
``subdivisions`` (default 8: 128 floor triangles).
"""
from __future__ import annotations

import numpy as np

from engine.core.errors import ConfigError
from engine.core.scene import Camera, Material, PointLight, SceneBuilder

from .catalog import LOADERS, scene_loader
from .erw6 import grid_quad

FLOOR = Material("mirror-floor", ambient=(0.05, 0.05, 0.05), diffuse=(0.35, 0.35, 0.35),
                 specular=(0.3, 0.3, 0.3), shininess=60.0, reflectance=(0.6, 0.6, 0.6))
BUNNY = Material("bunny", ambient=(0.1, 0.09, 0.08), diffuse=(0.8, 0.72, 0.6),
                 specular=(0.2, 0.2, 0.2), shininess=30.0)


@scene_loader("bunny-floor")
def bunny_floor_scene(files, params, time):
    floor_size = params.get("floor_size", 6.0)
    if isinstance(floor_size, bool) or not isinstance(floor_size, (int, float)) or not 1 <= floor_size <= 1000:
        raise ConfigError(f"bunny-floor: floor_size must be a number in 1..1000, got {floor_size!r}")
    subdivisions = params.get("subdivisions", 8)
    if isinstance(subdivisions, bool) or not isinstance(subdivisions, int) or not 1 <= subdivisions <= 1024:
        raise ConfigError(f"bunny-floor: subdivisions must be an integer in 1..1024, got {subdivisions!r}")
    bunny = LOADERS["mesh"](files, {}, time)
    lo, hi = bunny.bounds()
    height = float(hi[1] - lo[1])
    centre = (lo + hi) / 2
    side = floor_size * height
    builder = SceneBuilder("bunny-floor", source=bunny.source)
    builder.add_material(BUNNY)
    floor = builder.add_material(FLOOR)
    builder.add_triangles(bunny.triangles._replace(material=np.zeros_like(bunny.triangles.material)))
    # u x v points up (+y): the floor faces the bunny.
    origin = (centre[0] - side / 2, lo[1], centre[2] - side / 2)
    vertices, faces = grid_quad(origin, (0.0, 0.0, side), (side, 0.0, 0.0), subdivisions)
    builder.add_mesh(vertices, faces, floor)
    eye = centre + np.array([0.0, 0.9, 2.6]) * height
    look_at = centre - np.array([0.0, 0.25, 0.0]) * height
    light = PointLight(tuple(centre + np.array([1.2, 3.0, 1.5]) * height), (1.0, 1.0, 1.0))
    info = {"lod": params.get("lod", 0), "bunny_triangles": bunny.n_triangles,
            "floor_triangles": 2 * subdivisions ** 2}
    return builder.build(camera=Camera(tuple(eye), tuple(look_at), (0.0, 1.0, 0.0), 45.0), lights=[light],
                         background=(0.3, 0.4, 0.55), ambient_light=(1.0, 1.0, 1.0), info=info)

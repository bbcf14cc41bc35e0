"""The ``--stats`` document of a render (``packetrt render --stats``, ``RayTracer.render``)."""
from __future__ import annotations

from engine.core.types import RAY_KINDS


def stats_dict(scene, config, result) -> dict:
    """The --stats document (see the README for its fields) of ``result`` (a RenderResult of
    ``scene`` rendered with ``config``)."""
    return {
        "scene": scene.name, "triangles": scene.n_triangles,
        "width": config.render.width, "height": config.render.height,
        "config": config.to_dict(),
        "seconds": result.seconds,
        "rays": result.rays,
        "mrays_per_s": result.mrays_per_s(),
        "counters": {name: result.counters.get(name, dict.fromkeys(RAY_KINDS, 0))
                     for name in ("ray_aabb", "ray_tri")},
        "counters_by_depth": result.counters_by_depth,
        "counters_from": "a separate counting pass over the same rays (timings exclude counting)",
        "extra": result.extra,
    }

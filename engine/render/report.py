"""The ``--stats`` document of a render (``packetrt render --stats``, ``RayTracer.render``)."""
from __future__ import annotations

import numpy as np

from engine.core.types import RAY_KINDS


def frames_dict(seconds: list) -> dict:
    """{"n", "seconds", "median", "fps"} of whole-frame times (seconds per frame)."""
    median = float(np.median(seconds))
    return {"n": len(seconds), "seconds": [float(s) for s in seconds], "median": median,
            "fps": 1.0 / median if median > 0 else None}


def stats_dict(scene, config, result, frames: list | None = None) -> dict:
    """The --stats document (see the README for its fields) of ``result`` (a RenderResult of
    ``scene`` rendered with ``config``); ``frames``: every timed frame's seconds (default: the
    one of ``result``)."""
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
        "frames": frames_dict(frames or [result.seconds["total"]]),
    }

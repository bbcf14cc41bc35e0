"""The ``--stats`` document of a render (``packetrt render --stats``, ``RayTracer.render``)."""
from __future__ import annotations

import numpy as np

from engine.core.threads import thread_count
from engine.core.types import RAY_KINDS


def frames_dict(seconds: list) -> dict:
    """{"n", "seconds", "median", "fps"} of whole-frame times (seconds per frame)."""
    median = float(np.median(seconds))
    return {"n": len(seconds), "seconds": [float(s) for s in seconds], "median": median,
            "fps": 1.0 / median if median > 0 else None}


def extra_dict(scene, result) -> dict:
    """The ``extra`` field: what a run knows beyond the counters -- plugin statistics per ray
    kind (filled by a counting pass: ``rayspace`` pair streams, ``embree`` version; {} for
    plugins that keep none), the scene's re-centring shift (``origin``, [0, 0, 0] unless the
    scene lay far from the origin), the loader's warnings (a missing texture) and the end each
    light's shadow rays were walked from (``shadow_order``: {"LIGHT/KIND": "surface" |
    "light"}, ``engine.render.shadow_order``)."""
    return {"plugins": result.extra, "scene_origin": list(scene.origin),
            "scene_warnings": list(scene.info.get("warnings", [])),
            "shadow_order": dict(getattr(result, "shadow_order", {}))}


#: ``counters_from`` of a render's --stats: where its counters come from.
COUNTED = "a separate counting pass over the same rays (timings exclude counting)"
#: ... and of an audited frame (``render --audit``), which no counting pass follows.
NOT_COUNTED = "none: an audited frame (render --audit) is not counted, and its times include the checking"
#: ... and of a frame on the GPU, whose kernels keep no traversal counters.
DEVICE_NOT_COUNTED = "none: the GPU's kernels keep no traversal counters (every counter is 0)"


def stats_dict(scene, config, result, frames: list | None = None, audited: bool = False) -> dict:
    """The --stats document (see the README for its fields) of ``result`` (a RenderResult of
    ``scene`` rendered with ``config``); ``frames``: every timed frame's seconds (default: the
    one of ``result``). ``audited``: the frame of an audit (counters zero, times with the
    checking in them), said so in ``counters_from`` and ``audited``."""
    return {
        "scene": scene.name, "triangles": scene.n_triangles,
        "width": config.render.width, "height": config.render.height,
        "config": config.to_dict(),
        # The threads the kernels ran on: the config's count, capped by numba's pool
        # (NUMBA_NUM_THREADS), which config.render.threads alone does not show.
        "threads": thread_count(config.render.threads),
        "seconds": result.seconds,
        "rays": result.rays,
        "mrays_per_s": result.mrays_per_s(),
        "counters": {name: result.counters.get(name, dict.fromkeys(RAY_KINDS, 0))
                     for name in ("ray_aabb", "ray_tri")},
        "counters_by_depth": result.counters_by_depth,
        "counters_from": NOT_COUNTED if audited else DEVICE_NOT_COUNTED if config.render.device == "cuda" else COUNTED,
        "audited": audited,
        "extra": extra_dict(scene, result),
        "frames": frames_dict(frames or [result.seconds["total"]]),
    }

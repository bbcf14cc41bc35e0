"""Run under numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``, in its own process): the GPU
frame of a tiny scene against the CPU renderer, and every ray it casts against Embree.

Prints one JSON object; ``tests/test_gpu_frame.py`` runs it and checks the numbers. Usage:
``python -m tests.gpu_sim_frame_check WIDTH HEIGHT TRAVERSAL [MAX_DEPTH [textured | ORDER]]``, ORDER
a ``[render] shadow_order`` ("surface", "light", "auto").
"""
from __future__ import annotations

import json
import sys

import numpy as np

from tests.cudasim import prepare


def _textured(scene):
    """``scene`` with texture coordinates on every triangle (planar in x and z, negative ones
    included, so lookups wrap) and a small texture on every material: the texel path of the
    shading (``texel_at``) on both targets."""
    from dataclasses import replace

    tris = scene.triangles
    corners = np.stack([tris.v0, tris.v1, tris.v2], axis=1)            # (T, 3, 3)
    uvs = np.ascontiguousarray(corners[:, :, [0, 2]] * np.float32(0.37), np.float32)
    rng = np.random.default_rng(5)
    materials = [replace(m, texture=rng.random((5, 7, 3)).astype(np.float32)) for m in scene.materials]
    return replace(scene, triangles=tris._replace(uvs=uvs), materials=materials)


def main(width: int, height: int, traversal: str, depth: int, textured: bool = False, shadow_order: str = "auto") -> dict:
    prepare()
    from engine.gpu.frame import GpuWhittedRenderer
    from engine.render.config import Config, RenderConfig, PerKind
    from engine.render.whitted import WhittedRenderer
    from scenes.catalog import load_named
    from validation.audit import AuditObserver, make_oracle

    scene = load_named("whitted", {"checks": 2, "subdivisions": 0})
    if textured:
        scene = _textured(scene)
    render = RenderConfig(width=width, height=height, max_depth=depth, packet=4)
    cpu_config = Config(render=render, traversal=PerKind("single", "single", "single", "single"),
                        frustum=PerKind("none", "none", "none", "none"))
    cpu = WhittedRenderer(scene, cpu_config).render()
    gpu_config = Config(render=RenderConfig(width=width, height=height, max_depth=depth, packet=4, device="cuda",
                                            shadow_order=shadow_order),
                        traversal=PerKind(*[traversal] * 4), frustum=PerKind("none", "none", "none", "none"))
    gpu_renderer = GpuWhittedRenderer(scene, gpu_config)
    observer = AuditObserver(scene, gpu_renderer.bvh, [make_oracle("embree", scene.triangles)])
    gpu_renderer.observer = observer
    gpu = gpu_renderer.render()
    report = observer.report()
    difference = np.abs(cpu.image - gpu.image)
    return {"triangles": scene.n_triangles, "rays_cpu": cpu.rays, "rays_gpu": gpu.rays,
            "max_abs_difference": float(difference.max()),
            "pixels_over_1_255": int((difference.max(axis=2) > 1 / 255).sum()),
            "image_nonzero": int((gpu.image.max(axis=2) > 0).sum()), "image_mean": float(gpu.image.mean()),
            "audit_checked": report["rays_checked"], "audit_mismatches": report["mismatch_count"],
            "audit_by_kind": report["by_kind"], "traversal": gpu.extra["device"]["traversal"],
            "shadow_far_first": getattr(gpu_renderer.traversal["shadow"], "far_first", None)}


if __name__ == "__main__":
    args = sys.argv[1:]
    extra = args[4] if len(args) > 4 else ""
    result = main(int(args[0]), int(args[1]), args[2], int(args[3]) if len(args) > 3 else 3, extra == "textured",
                  extra if extra in ("surface", "light", "auto") else "auto")
    print(json.dumps(result))

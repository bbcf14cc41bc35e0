"""Run under numba's CUDA simulator (in its own process): a device frame that switches to a
refit of its tree (an animation's next frame) whose 8-wide collapse merges other nodes -- the
same binary topology, the same wide node count, other links -- against the CPU frame and a fresh
device frame of that scene. Prints one JSON object (``tests/test_gpu_animate.py`` checks it)."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np


def main() -> dict:
    import trimesh

    from engine import RayTracer
    from engine.core.bvh import build_bvh
    from engine.core.bvh_refit import refit_bvh
    from engine.core.scene import make_triangles
    from engine.gpu.frame import GpuWhittedRenderer
    from engine.gpu.wide_trace import wide_tables
    from engine.render.config import Config, PerKind, RenderConfig
    from engine.render.whitted import WhittedRenderer

    mesh = trimesh.creation.icosphere(subdivisions=2)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    stretched = vertices * np.array([1.25, 1.0, 1 / 1.15])   # the next frame: the sphere stretched
    first = RayTracer((vertices, faces)).scene
    second = replace(first, triangles=make_triangles(stretched, faces, 0))
    bvh = build_bvh(first.triangles, leaf_size=4, bins=16)
    refit = refit_bvh(bvh, second.triangles)
    (box_a, links_a), (box_b, links_b) = wide_tables(bvh), wide_tables(refit)

    def config(device, traversal):
        return Config(render=RenderConfig(width=16, height=16, max_depth=1, device=device),
                      traversal=PerKind(*[traversal] * 4))

    cpu = WhittedRenderer(second, config("cpu", "wide"), bvh=refit).render().image
    differing = {}
    for traversal in ("bvh", "wide"):
        gpu = GpuWhittedRenderer(first, config("cuda", traversal), bvh=bvh)
        gpu.render()
        gpu.set_scene(second, refit)   # the animation's refit path
        image = gpu.render().image
        differing[traversal] = int((np.abs(image - cpu).max(axis=2) > 1e-5).sum())
    return {"same_wide_nodes": box_a.shape[0] == box_b.shape[0], "same_links": bool(np.array_equal(links_a, links_b)),
            "differing_pixels": differing}


if __name__ == "__main__":
    print(json.dumps(main()))

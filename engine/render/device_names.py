"""Which device traversal a config's traversal name selects on ``device = "cuda"``.

On ``device = "cuda"`` a kind's traversal is ``bvh`` (``engine.gpu.bvh_trace``, a per-ray
stack walk of the shared BVH), ``wide`` (``engine.gpu.wide_trace``, a per-ray walk of the
8-wide tree collapsed from it, as the CPU's ``wide``) or ``rayspace`` (``engine.gpu.rayspace``,
Roger et al.'s hierarchy over the rays). The CPU's other BVH traversals (single, masked, ranged,
partition, simd, auto) are ways of walking the same tree with CPU SIMD lanes; they all return
the same hits, and on the device their names select ``bvh``, so a CPU config runs on the GPU
unchanged.
"""
from __future__ import annotations

from engine.core.errors import ConfigError

DEVICE_TRAVERSALS = ("bvh", "wide", "rayspace")
#: CPU traversal names that walk the BVH and so run as ``bvh`` on the device.
CPU_BVH_TRAVERSALS = ("single", "masked", "ranged", "partition", "simd", "auto")


def device_traversal_name(name: str, kind: str = "") -> str:
    """The device traversal a config name selects; ConfigError for one with no CUDA version."""
    if name in DEVICE_TRAVERSALS:
        return name
    if name in CPU_BVH_TRAVERSALS:
        return "bvh"
    where = f"traversal.{kind}" if kind else "traversal"
    raise ConfigError(f"{where} {name!r} has no CUDA version; on device 'cuda' use one of: "
                      f"{', '.join(DEVICE_TRAVERSALS)} (the CPU BVH traversals "
                      f"{', '.join(CPU_BVH_TRAVERSALS)} run as bvh)")

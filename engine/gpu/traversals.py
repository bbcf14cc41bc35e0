"""The device traversal instances of a config, one per name (``engine.render.device_names``
says which name selects which)."""
from __future__ import annotations

import functools

from engine.core.types import RAY_KINDS
from engine.render.device_names import device_traversal_name


#: ``[render] shadow_order`` on the device: does the BVH walk of shadow rays take the child the
#: ray enters later (nearer the light) first. The device has no per-light trials as the CPU
#: frame has (``engine.render.shadow_order``); "auto" takes the light end, measured on an H200
#: (session 19, kernel time of the kitchen's shadow rays at 1024²): to light 0 0.361 -> 0.271 ms,
#: to all six lights 1.858 -> 1.504 ms, the same answers; whole frames kitchen with six lights
#: 5.8 -> 5.4 ms, the default scene, bunny and kitchen-paper within noise, the Cornell box
#: 2.0-2.2 -> 2.2 ms.
WALKS_FAR_FIRST = {"surface": False, "light": True, "auto": True}


def walks_far_first(shadow_order: str) -> bool:
    """Whether the device's shadow walks take the far child first under ``shadow_order``."""
    return WALKS_FAR_FIRST[shadow_order]


def device_traversals(config, device_bvh, device_tris, host_tris) -> dict:
    """{ray kind: device traversal instance} for ``config``; kinds that name the same traversal
    share one instance (only shadow rays ask it for occlusion, so the BVH walk's far-first
    order, ``[render] shadow_order``, is theirs)."""
    made = {}
    chosen = {}
    far_first = walks_far_first(config.render.shadow_order)
    for kind in RAY_KINDS:
        name = device_traversal_name(config.traversal.get(kind), kind)
        if name not in made:
            options = dict(dict(config.options).get("rayspace", ())) if name == "rayspace" else None
            made[name] = make_device_traversal(name, device_bvh, device_tris, host_tris, options, far_first)
        chosen[kind] = made[name]
    return chosen


class HostCounted:
    """A traversal that needs its ray count on the host (the ray-space hierarchy sizes its
    levels and streams from it), given the frame's device-counted queue interface: it reads the
    count back (one wait for the GPU per queue) and calls ``closest`` / ``occluded``."""

    def __init__(self, traversal):
        self.traversal = traversal
        self.name = getattr(traversal, "name", "rayspace")

    def __getattr__(self, attribute):
        return getattr(self.traversal, attribute)

    @staticmethod
    def _n(count, bound) -> int:
        return min(int(count.copy_to_host()[0]), bound)

    def closest_queue(self, org, dirs, tmin, tmax, pixel, count, bound, width, height, *out, secondary=False) -> None:
        n = self._n(count, min(bound, org.shape[0]))
        if n > 0:
            self.traversal.closest(org, dirs, tmin, tmax, pixel, n, width, height, *out, secondary=secondary)

    def occluded_queue(self, org, dirs, tmin, tmax, pixel, count, bound, width, height, out, light=None) -> None:
        n = self._n(count, min(bound, org.shape[0]))
        if n > 0:
            self.traversal.occluded(org, dirs, tmin, tmax, pixel, n, width, height, out, light=light)

    def queue_launch(self, query: str, *args, light=None, secondary=False):
        """A callable running ``closest_queue`` / ``occluded_queue`` on these arguments
        (``light``: the point every shadow ray aims at, when there is one; ``secondary``: the
        closest-hit queue holds reflection and refraction rays)."""
        if query == "closest":
            return functools.partial(self.closest_queue, *args, secondary=secondary)
        return functools.partial(self.occluded_queue, *args, light=light)


def make_device_traversal(name: str, device_bvh, device_tris, host_tris, options: dict | None = None,
                          far_first: bool = False):
    """One device traversal by name ("bvh", "wide", "rayspace", or a CPU BVH traversal name);
    far_first: the binary BVH walk's occlusion order (see ``WALKS_FAR_FIRST``; ``wide`` visits
    a node's children nearest first)."""
    name = device_traversal_name(name)
    if name == "bvh":
        from engine.gpu.bvh_trace import DeviceBVHTraversal

        return DeviceBVHTraversal(device_bvh, device_tris, far_first)
    if name == "wide":
        from engine.gpu.wide_trace import DeviceWideTraversal

        if device_bvh.host_bvh is None:
            raise ValueError("the device wide traversal needs the host tree the DeviceBVH was uploaded from")
        return DeviceWideTraversal(device_bvh, device_tris, device_bvh.host_bvh)
    from engine.gpu.rayspace import DeviceRaySpace

    return HostCounted(DeviceRaySpace(device_tris, host_tris, **(options or {})))

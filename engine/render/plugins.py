"""The composition root: config names -> new, configured plugin instances.

The renderer's one door to the built-in plugin packages (``traversals``, ``frusta``; importing
them registers their classes in ``engine.core.registry``); the only other importer is
``engine.debug.packet_trace``, which draws walks with ``traversals.single``'s and
``traversals.rayspace``'s own kernels. Every call makes a new instance, so
the options of one config (``[options.rayspace] pair_budget``, ``[options.embree] robust``)
live in the instances that config's renderer holds and die with it.
"""
from __future__ import annotations

import frusta  # noqa: F401  (registers the built-in frustum builders)
import traversals  # noqa: F401  (registers the built-in traversals)
from engine.core import registry


def make_traversal(name: str, options: dict | None = None):
    """A new traversal plugin ``name`` configured with ``options`` ({key: value}; None: the
    defaults). Unknown name, key or bad value: ConfigError."""
    return registry.instantiate(registry.factory(registry.TRAVERSALS, name, "traversal"), name, options)


def make_frustum(name: str):
    """A new frustum builder ``name``; unknown name: ConfigError listing the registered ones."""
    return registry.instantiate(registry.factory(registry.FRUSTA, name, "frustum"), name, None)


def traversal_names() -> list[str]:
    return sorted(registry.TRAVERSALS)


def frustum_names() -> list[str]:
    return sorted(registry.FRUSTA)


def load_entry_points() -> list[str]:
    """Third-party plugins from the ``packetrt.traversals`` / ``packetrt.frusta`` entry points."""
    return registry.load_entry_points()


def describe() -> dict:
    """{"traversals": [{"name", "doc"}], "frusta": [...]} for ``packetrt plugins``."""
    return {"traversals": registry.describe_table(registry.TRAVERSALS),
            "frusta": registry.describe_table(registry.FRUSTA)}


def uses_bvh(config) -> bool:
    """Whether any ray kind's traversal reads the engine's BVH (plugins that do not say
    ``uses_bvh = False``: Embree and the ray-space hierarchy keep no scene tree of ours)."""
    from engine.core.types import RAY_KINDS

    if getattr(config.render, "device", "cpu") == "cuda":   # the device's names: bvh, wide, rayspace
        from engine.render.device_names import device_traversal_name

        return any(device_traversal_name(config.traversal.get(k), k) != "rayspace" for k in RAY_KINDS)
    classes = {registry.factory(registry.TRAVERSALS, config.traversal.get(k), "traversal") for k in RAY_KINDS}
    return any(getattr(cls, "uses_bvh", True) for cls in classes)


def configured(config) -> tuple[dict, dict]:
    """({ray kind: traversal}, {ray kind: frustum builder}) for ``config``: one new instance per
    distinct name, shared by the kinds that name it (an Embree scene is then built once)."""
    from engine.core.types import RAY_KINDS

    options = {name: dict(table) for name, table in config.options}
    travs = {name: make_traversal(name, options.get(name)) for name in {config.traversal.get(k) for k in RAY_KINDS}}
    frusts = {name: make_frustum(name) for name in {config.frustum.get(k) for k in RAY_KINDS}}
    return ({k: travs[config.traversal.get(k)] for k in RAY_KINDS},
            {k: frusts[config.frustum.get(k)] for k in RAY_KINDS})

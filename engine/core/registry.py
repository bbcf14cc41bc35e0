"""Plugin registry: config names -> traversal and frustum plugins.

A traversal plugin is a module-level object with two methods::

    intersect(bvh, tris, rays, packets, frusta, hits, stats) -> None   # closest hit
    occluded(bvh, tris, rays, packets, frusta, occluded, stats) -> None  # any hit

that fill the output arrays in place (``stats`` may be None: no counting). A frustum
plugin has ``build(rays, packets, scene_bounds) -> Frusta``.

Built-in plugins register on import of the ``traversals`` and ``frusta`` packages.
Third-party packages add plugins through the entry-point groups ``packetrt.traversals``
and ``packetrt.frusta``; those are loaded only when asked (``load_entry_points``).
"""
from __future__ import annotations

from importlib import metadata

from engine.core.errors import ConfigError

TRAVERSALS: dict = {}
FRUSTA: dict = {}

ENTRY_POINT_GROUPS = {"traversal": "packetrt.traversals", "frustum": "packetrt.frusta"}


def register_traversal(name: str):
    """Class or instance decorator: ``@register_traversal("partition")``."""
    return _registrar(TRAVERSALS, name)


def register_frustum(name: str):
    """Class or instance decorator: ``@register_frustum("pinhole")``."""
    return _registrar(FRUSTA, name)


def _registrar(table: dict, name: str):
    def decorate(plugin):
        instance = plugin() if isinstance(plugin, type) else plugin
        instance.name = name
        table[name] = instance
        return plugin

    return decorate


def _ensure_builtins_loaded() -> None:
    # Importing the packages registers the built-in plugins; done lazily so that
    # engine modules can import the registry without a cycle.
    import frusta  # noqa: F401
    import traversals  # noqa: F401


def get_traversal(name: str):
    """The traversal plugin registered as ``name``; ConfigError listing names if unknown."""
    _ensure_builtins_loaded()
    return _lookup(TRAVERSALS, name, "traversal")


def get_frustum(name: str):
    """The frustum plugin registered as ``name``; ConfigError listing names if unknown."""
    _ensure_builtins_loaded()
    return _lookup(FRUSTA, name, "frustum")


def _lookup(table: dict, name: str, what: str):
    if name not in table:
        allowed = ", ".join(sorted(table))
        raise ConfigError(f"unknown {what} {name!r}; registered {what}s: {allowed}")
    return table[name]


def traversal_names() -> list[str]:
    _ensure_builtins_loaded()
    return sorted(TRAVERSALS)


def frustum_names() -> list[str]:
    _ensure_builtins_loaded()
    return sorted(FRUSTA)


def load_entry_points() -> list[str]:
    """Import third-party plugins from the entry-point groups; returns what was loaded.

    A plugin that fails to import is reported as a ConfigError naming the entry point.
    """
    _ensure_builtins_loaded()
    loaded = []
    for group in ENTRY_POINT_GROUPS.values():
        for entry in metadata.entry_points(group=group):
            try:
                entry.load()
            except Exception as exc:  # a broken third-party plugin is a user-facing problem
                raise ConfigError(f"plugin entry point {entry.name!r} ({entry.value}) in group "
                                  f"{group!r} failed to load: {exc}") from exc
            loaded.append(f"{group}:{entry.name}")
    return loaded


def describe() -> dict:
    """{"traversals": [{"name", "doc"}], "frusta": [...]} for ``packetrt plugins``."""
    _ensure_builtins_loaded()

    def rows(table):
        return [{"name": n, "doc": (type(p).__doc__ or "").strip().splitlines()[0]
                 if (type(p).__doc__ or "").strip() else ""} for n, p in sorted(table.items())]

    return {"traversals": rows(TRAVERSALS), "frusta": rows(FRUSTA)}

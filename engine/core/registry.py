"""Plugin registry: config names -> plugin *factories* (classes), never instances.

A traversal plugin is a class whose instances answer two queries::

    intersect(bvh, tris, rays, packets, frusta, hits, stats) -> None   # closest hit
    occluded(bvh, tris, rays, packets, frusta, occluded, stats) -> None  # any hit

filling the output arrays in place (``stats`` may be None: no counting). A frustum plugin's
instances have ``build(rays, packets, scene_bounds) -> Frusta``. A plugin that takes options
declares their defaults in a class attribute ``OPTIONS`` ({key: default}) and accepts them as
keyword arguments of ``__init__``, checking the values (ConfigError).

This module only keeps the tables: it imports no plugin package. ``engine.render.plugins``
(the composition root) imports the built-in ``traversals`` and ``frusta`` packages, whose
``@register_traversal`` / ``@register_frustum`` decorators fill the tables, and hands out a
new configured instance per request, so nothing one config sets reaches another.
"""
from __future__ import annotations

from importlib import metadata

from engine.core.errors import ConfigError, ConfigTypeError

TRAVERSALS: dict = {}
FRUSTA: dict = {}

ENTRY_POINT_GROUPS = {"traversal": "packetrt.traversals", "frustum": "packetrt.frusta"}


def register_traversal(name: str):
    """Class decorator: ``@register_traversal("partition")`` makes the class the factory for
    config name "partition" (and sets its ``name``)."""
    return _registrar(TRAVERSALS, name)


def register_frustum(name: str):
    """Class decorator: ``@register_frustum("pinhole")``."""
    return _registrar(FRUSTA, name)


def _registrar(table: dict, name: str):
    def decorate(cls):
        if not isinstance(cls, type):
            raise TypeError(f"plugin {name!r}: register a class (a factory), not {type(cls).__name__} instance")
        cls.name = name
        table[name] = cls
        return cls

    return decorate


def factory(table: dict, name: str, what: str) -> type:
    """The class registered as ``name`` in ``table``; ConfigError listing the names if unknown
    (ConfigTypeError for a name that is not a string)."""
    if not isinstance(name, str):
        raise ConfigTypeError(f"a {what} is named by a string ({', '.join(sorted(table))}), got {name!r}")
    if name not in table:
        allowed = ", ".join(sorted(table))
        raise ConfigError(f"unknown {what} {name!r}; registered {what}s: {allowed}")
    return table[name]


def instantiate(cls: type, name: str, options: dict | None):
    """A new instance of plugin class ``cls`` configured with ``options`` (None: defaults).
    Keys the class does not declare in ``OPTIONS`` are a ConfigError naming the allowed ones."""
    options = dict(options or {})
    allowed = getattr(cls, "OPTIONS", {})
    unknown = set(options) - set(allowed)
    if unknown and not allowed:
        raise ConfigError(f"options.{name}: {name!r} takes no options, got {sorted(unknown)}")
    if unknown:
        raise ConfigError(f"options.{name}: unknown key(s) {sorted(unknown)}; allowed: {', '.join(sorted(allowed))}")
    return cls(**options)


def load_entry_points() -> list[str]:
    """Import third-party plugins from the entry-point groups; returns what was loaded.

    A plugin that fails to import is reported as a ConfigError naming the entry point.
    """
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


def describe_table(table: dict) -> list:
    """[{"name", "doc"}] for the classes of ``table``, by name; doc is the docstring's first
    paragraph on one line (its first line alone cut the general frustum's sentence in two)."""
    def first_paragraph(cls):
        doc = (cls.__doc__ or "").strip()
        return " ".join(doc.split("\n\n")[0].split())

    return [{"name": n, "doc": first_paragraph(cls)} for n, cls in sorted(table.items())]

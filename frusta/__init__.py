"""Frustum plugins, one per file; the file name is the config name.

Importing this package registers every built-in frustum builder.
"""
from importlib import import_module

BUILTIN = ["none", "pinhole", "pointlight", "general"]

for _name in BUILTIN:
    import_module(f"{__name__}.{_name}")

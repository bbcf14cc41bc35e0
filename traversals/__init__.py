"""Traversal plugins, one per file; the file name is the config name.

Importing this package registers every built-in traversal.
"""
from importlib import import_module

BUILTIN = ["single", "wide", "embree", "rayspace", "simd", "masked", "ranged", "partition", "auto"]

for _name in BUILTIN:
    import_module(f"{__name__}.{_name}")

"""The scene a benchmark cell renders: catalog scenes loaded once for consecutive cells
(``SceneCache``) and a cell's recursion preset applied to them (``cell_scene``). Shared by the
runner, the ``auto`` fit and the paired frames.
"""
from __future__ import annotations

import gc
from dataclasses import replace

from engine.bench.matrix import Cell


class SceneCache:
    """The last loaded catalog scene (cells come sorted by scene, so one is enough)."""

    def __init__(self):
        self.key, self.scene = None, None

    def get(self, spec):
        from scenes.catalog import load_named

        key = (spec.name, spec.params, spec.time)
        if key != self.key:
            self.scene = None
            gc.collect()
            self.key, self.scene = key, load_named(spec.name, dict(spec.params), spec.time)
        return self.scene


def cell_scene(base, cell: Cell):
    """The scene a cell renders: its recursion preset's material override and point lights (none,
    all, or the first ``max_lights`` in the scene's order; a scene with fewer is a ConfigError)."""
    from engine.core.errors import ConfigError
    from engine.core.scene import override_materials

    preset = cell.preset
    scene = override_materials(base, preset.override)
    if not preset.lights:
        return replace(scene, lights=[])
    if preset.max_lights is None:
        return scene
    if preset.max_lights > len(scene.lights):
        raise ConfigError(f"recursion preset {cell.recursion!r} keeps the first {preset.max_lights} point "
                          f"light(s), but scene {cell.scene.label!r} has {len(scene.lights)}")
    return replace(scene, lights=list(scene.lights[:preset.max_lights]))

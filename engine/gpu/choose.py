"""The one place a render's device is chosen: ``new_renderer(scene, config, **kw)`` gives the
CPU ``WhittedRenderer`` or, for ``[render] device = "cuda"``, the GPU wavefront renderer
(imported only then, so the CPU path never touches CUDA)."""
from __future__ import annotations

from engine.render.whitted import WhittedRenderer


def new_renderer(scene, config, **kwargs):
    """A renderer for ``config.render.device`` (keyword arguments as ``WhittedRenderer``'s)."""
    if config.render.device == "cuda":
        from engine.gpu.frame import GpuWhittedRenderer

        return GpuWhittedRenderer(scene, config, **kwargs)
    return WhittedRenderer(scene, config, **kwargs)

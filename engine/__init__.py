"""packetrt's shared core: contracts, scene model, BVH, kernels, Whitted loop, config, CLI."""

from .jit_cache import invalidate_stale_caches as _invalidate_stale_caches

# Before any kernel loads from numba's cache: drop caches compiled against changed callees.
_invalidate_stale_caches()

__all__ = ["RayTracer", "RayInputError"]


def __getattr__(name):
    # The Python API (engine.api) loads on first use, so `import engine` stays cheap.
    if name in __all__:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'engine' has no attribute {name!r}")

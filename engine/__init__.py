"""packetrt: a Whitted ray tracer whose hot loops are numba kernels, with plugin traversals.

The public faces sit here: ``engine.api`` (``RayTracer``, ``RayMeshIntersector``, ``RayInputError``) and ``engine.cli``
(the ``packetrt`` command). The layers below, from the bottom up: ``engine.core`` (contracts,
scene, BVH, triangle test, registry), ``engine.packet`` and ``engine.rayspace`` (the two papers'
machinery), the plugin packages ``traversals``, ``frusta`` and ``scenes``, ``engine.render``
(config, the Tracer, the Whitted loop), ``validation``, and the tools ``engine.bench`` and
``engine.debug``. docs/architecture.md walks a config word from the CLI down to a kernel.
"""

from engine.core.numba_settings import settings_problem as _settings_problem

# With a bad NUMBA_NUM_THREADS or NUMBA_THREADING_LAYER, numba cannot be imported at all: leave it
# unimported here, so that the packetrt command (engine.launch) can say so in one line.
if _settings_problem() is None:
    from engine.core.jit_cache import use_source_keyed_cache as _use_source_keyed_cache
    from engine.core.jit_dataflow_copies import use_shallow_dataflow_copies as _use_shallow_dataflow_copies
    from engine.core.jit_inlining import use_linear_inline_copies as _use_linear_inline_copies

    # Before any kernel module is imported: numba's cache folder is keyed by the compiled
    # sources, so a kernel never loads machine code compiled against an older callee. Writes
    # nothing.
    _use_source_keyed_cache()
    # numba's inliner copies a callee's whole scope once per block; once per copy gives the same
    # machine code in a fraction of the inlining time (engine/core/jit_inlining.py).
    _use_linear_inline_copies()
    # Its data-flow passes deep-copy sets of variable names, where copying each set is the same.
    _use_shallow_dataflow_copies()

__all__ = ["RayTracer", "RayInputError", "RayMeshIntersector"]


def __getattr__(name):
    # The Python API (engine.api) loads on first use, so `import engine` stays cheap.
    if name in __all__:
        from engine import api

        return getattr(api, name)
    raise AttributeError(f"module 'engine' has no attribute {name!r}")

"""The device's floating point, made the CPU's: no fused multiply-add contraction.

NVVM, the compiler numba-cuda hands kernels to, fuses ``a * b + c`` into one FMA instruction by
default (its ``-fma=1``): a different rounding from the CPU kernels, which LLVM compiles without
contraction. The watertight triangle test, the hit points and the ray offsets then differ in the
last bit between the two targets, so a ray that grazes an edge can hit on one and miss on the
other, and an image differs from the CPU's in a few hundred pixels of the kitchen.

numba-cuda has no per-kernel switch for it (``fastmath=False`` leaves NVVM's default on), so
``engine.gpu`` compiles with ``-fma=0`` by wrapping numba-cuda's NVVM entry point once per
process: every kernel compiled in this process afterwards, packetrt's and any other, gets IEEE
multiplies and adds, unless it asks for ``fastmath=True`` (which still turns fusion on). Set
``PACKETRT_CUDA_FMA=1`` to leave NVVM's default alone.
"""
from __future__ import annotations

import os

_INSTALLED = False


def install_no_fma() -> bool:
    """Compile CUDA kernels without FMA contraction from now on (idempotent); False when the
    user opted out or numba-cuda's NVVM entry point is not where this version expects it."""
    global _INSTALLED
    if _INSTALLED:
        return True
    if os.environ.get("PACKETRT_CUDA_FMA", "") == "1":
        return False
    try:
        from numba.cuda.cudadrv import nvvm
    except ImportError:
        return False
    compile_ir = getattr(nvvm, "compile_ir", None)
    if compile_ir is None:
        return False

    def compile_without_fma(llvmir, **options):
        if not options.get("fastmath"):
            options.setdefault("fma", False)
        return compile_ir(llvmir, **options)

    nvvm.compile_ir = compile_without_fma
    _INSTALLED = True
    return True

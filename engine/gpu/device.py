"""Is there a CUDA device, and how do arrays get onto it.

``require_cuda()`` is the one gate: it returns numba's ``cuda`` module when kernels can run
(a real GPU, or numba's simulator under ``NUMBA_ENABLE_CUDASIM=1``) and otherwise raises
``DeviceUnavailable`` with one line naming what is missing (the ``numba-cuda`` package, a
driver, a GPU), which the CLI prints with exit code 2.
"""
from __future__ import annotations

import os

from engine.core.errors import PacketrtError

#: Threads per block of every 1-D kernel launch (a multiple of the 32-lane warp).
BLOCK = 128


class DeviceUnavailable(PacketrtError):
    """``device = "cuda"`` was asked for on a machine that cannot run CUDA kernels."""


def simulated() -> bool:
    """True under numba's CUDA simulator (kernels run as Python threads on the CPU)."""
    return os.environ.get("NUMBA_ENABLE_CUDASIM", "") not in ("", "0")


def require_cuda():
    """numba's ``cuda`` module, ready to launch kernels; raises DeviceUnavailable otherwise."""
    try:
        from numba import cuda
    except ImportError as error:  # pragma: no cover - numba always ships a cuda shim
        raise DeviceUnavailable(f"device 'cuda' needs numba's CUDA target ({error}); "
                                "install packetrt[gpu]") from None
    if simulated():
        return cuda
    try:
        import numba_cuda  # noqa: F401  (the maintained CUDA target; numba's own is deprecated)
    except ImportError:
        raise DeviceUnavailable("device 'cuda' needs the numba-cuda package: pip install 'packetrt[gpu]'") from None
    try:
        available = cuda.is_available()
    except Exception as error:  # noqa: BLE001 - the driver layer raises many kinds
        raise DeviceUnavailable(f"device 'cuda': the CUDA driver did not start ({type(error).__name__}: "
                                f"{str(error).splitlines()[0] if str(error) else 'no detail'})") from None
    if not available:
        raise DeviceUnavailable("device 'cuda': no CUDA GPU or driver found on this machine "
                                "(use device = 'cpu', or NUMBA_ENABLE_CUDASIM=1 to simulate)")
    return cuda


def device_name() -> str:
    """The GPU's name ("simulator" under NUMBA_ENABLE_CUDASIM)."""
    cuda = require_cuda()
    if simulated():
        return "numba CUDA simulator"
    name = cuda.get_current_device().name
    return name.decode() if isinstance(name, bytes) else str(name)


def blocks(n: int) -> int:
    """Blocks of BLOCK threads that cover n items (at least one)."""
    return max(1, -(-int(n) // BLOCK))


def on_device(value):
    """A numba device array viewing ``value`` when it already lives on the GPU (a numba device
    array, or any object with ``__cuda_array_interface__``: torch, CuPy), without a copy; None
    for anything else (numpy arrays, lists, scalars)."""
    cuda = require_cuda()
    if cuda.devicearray.is_cuda_ndarray(value):
        return value
    if hasattr(value, "__cuda_array_interface__"):
        return cuda.as_cuda_array(value)
    return None

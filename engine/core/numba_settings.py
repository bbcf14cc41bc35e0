"""numba's environment settings, checked before numba is imported.

numba reads ``NUMBA_NUM_THREADS`` and ``NUMBA_THREADING_LAYER`` when it is first imported: a
count of 0 or a word there is numba's own traceback at ``import numba``, before the ``packetrt``
command can say anything, and a count in the tens of thousands crashed the process (SIGSEGV) or
took minutes to start. ``settings_problem`` reads the same variables with the standard library
only, so the command's entry point (``engine.launch``) can refuse them in one line.
"""
from __future__ import annotations

import os

#: The most threads packetrt asks for anywhere (a config's [render] threads: 0..1024).
MAX_THREADS = 1024
#: numba's threading layers and the words that choose among them.
THREADING_LAYERS = ("default", "safe", "forksafe", "threadsafe", "tbb", "omp", "workqueue")


def settings_problem(environ=None) -> str | None:
    """One line saying what is wrong with numba's environment variables, or None."""
    environ = os.environ if environ is None else environ
    threads = environ.get("NUMBA_NUM_THREADS")
    if threads is not None and threads.strip():
        if not threads.strip().isdigit() or not 1 <= int(threads) <= MAX_THREADS:
            return (f"environment variable NUMBA_NUM_THREADS={threads!r}: must be a whole number of threads "
                    f"in 1..{MAX_THREADS} (or unset: every core)")
    layer = environ.get("NUMBA_THREADING_LAYER")
    if layer is not None and layer.strip() and layer.strip().lower() not in THREADING_LAYERS:
        return (f"environment variable NUMBA_THREADING_LAYER={layer!r}: must be one of "
                f"{', '.join(THREADING_LAYERS)} (or unset)")
    return None


def hide_setup_warnings() -> None:
    """Silence two warnings about numba's set-up, not about the command: numba's note that this
    machine's TBB is too old for its TBB threading layer (it uses another; Open3D loads that
    TBB), and numba-cuda's note at every launch of fewer than 128 blocks (a GPU frame's small
    queues, scans and upper hierarchy levels are small by nature; a GPU bench printed dozens a
    scene). Called by the command line and by the tasks it sends to Dask workers, which are
    processes of their own."""
    import warnings

    warnings.filterwarnings("ignore", message=".*TBB threading layer.*")
    warnings.filterwarnings("ignore", message="Grid size .* will likely result in GPU under-utilization")

"""Cell-measuring functions the Dask tests hand to their workers (importable by name there)."""
from __future__ import annotations

import os
from pathlib import Path


def crash_once_then_run(cell, repeat, scene_cache, yardstick, machine, matrix_name, references, open3d=None):
    """Kill this worker process the first time any cell starts (a marker file in
    PACKETRT_TEST_CRASH_MARKER says it happened), as a machine lost mid-cell would; measure
    normally afterwards."""
    from engine.bench.runner import run_cell

    marker = Path(os.environ["PACKETRT_TEST_CRASH_MARKER"])
    try:
        marker.touch(exist_ok=False)
    except FileExistsError:
        return run_cell(cell, repeat, scene_cache, yardstick, machine, matrix_name, references, open3d=open3d)
    os._exit(17)  # no cleanup, no record: the worker is gone mid-cell

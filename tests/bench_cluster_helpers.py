"""Cell-measuring functions the Dask tests hand to their workers (importable by name there)."""
from __future__ import annotations

import os
from pathlib import Path


def crash_once_then_run(cell, repeat, scene_cache, yardstick, machine, matrix_name, references, open3d=None,
                        marker=None):
    """Kill this worker process the first time any cell starts (the file ``marker`` says it
    happened), as a machine lost mid-cell would; measure normally afterwards. Bound with
    ``functools.partial`` so the path travels with the task to workers started before it was
    chosen."""
    from engine.bench.runner import run_cell

    marker = Path(marker)
    try:
        marker.touch(exist_ok=False)
    except FileExistsError:
        return run_cell(cell, repeat, scene_cache, yardstick, machine, matrix_name, references, open3d=open3d)
    os._exit(17)  # no cleanup, no record: the worker is gone mid-cell


def crash_on_cell(cell, repeat, scene_cache, yardstick, machine, matrix_name, references, open3d=None, key=None):
    """Kill this worker process whenever the cell ``key`` starts (a cell that takes its machine
    down every time, as one that runs out of memory would); measure the others normally."""
    from engine.bench.runner import run_cell

    if cell.key == key:
        os._exit(17)
    return run_cell(cell, repeat, scene_cache, yardstick, machine, matrix_name, references, open3d=open3d)

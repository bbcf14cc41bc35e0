"""Benchmark cells as Dask tasks: ``packetrt bench M.toml --scheduler [ADDRESS]``.

Each cell is one task. A worker measures the cell and its Embree yardstick in that one task,
with its own scene cache and yardsticks, and puts its own machine (CPU model, cores, numba
threads) into the record, so a row's ratios never mix two machines. Only the client writes
``results.jsonl``, one finished record at a time as tasks complete: a worker lost mid-cell
leaves nothing behind, and Dask runs the cell again elsewhere (its scheduler re-submits the
tasks of a lost worker), so no cell is lost or recorded twice; ``--resume`` skips the cells
already written, whichever scheduler wrote them.

With no address a local cluster is started on this machine: one worker process, one task at a
time by default, so a cell's timings are not disturbed by another's (``--workers N`` runs N at
once, for checks rather than timings). An address (``tcp://host:8786``) points at a running
``dask scheduler`` whose workers have packetrt installed and the scene files on their
``PACKETRT_SCENE_PATH``.
"""
from __future__ import annotations

from engine.core.errors import ConfigError

#: ``--scheduler`` with no address.
LOCAL = "local"


def connect(address: str, workers: int = 1):
    """(client, local cluster or None) for ``address`` (LOCAL: start one of ``workers`` worker
    processes here). A missing dask or an unreachable scheduler is a ConfigError."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ConfigError("--scheduler needs dask.distributed: pip install 'packetrt[cluster]'") from None
    if not 1 <= workers <= 256:
        raise ConfigError(f"--workers must be in 1..256, got {workers}")
    if address == LOCAL:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
        return Client(cluster), cluster
    try:
        return Client(address, timeout="15s"), None
    except (OSError, TimeoutError, ValueError) as error:
        raise ConfigError(f"--scheduler {address}: cannot reach a Dask scheduler there "
                          f"({type(error).__name__}: {error})") from None


def cell_task(cell, repeat: int, matrix_name: str, run=None) -> dict:
    """On a worker: measure one cell with fresh caches and yardsticks (``run``: the measuring
    function, default ``runner.run_cell``); returns its results.jsonl record, stamped with the
    worker's machine."""
    from engine.bench import runner

    run = run or runner.run_cell
    yardstick, open3d = runner.EmbreeYardstick(), runner.Open3DYardstick()
    try:
        return run(cell, repeat, runner.SceneCache(), yardstick, runner.machine_info(), matrix_name,
                   runner.ReferenceAnswers(), open3d=open3d)
    finally:
        yardstick.close()
        open3d.close()


def run_on_cluster(client, cells: list, repeat: int, matrix_name: str, record, run=None) -> int:
    """Submit every cell, then hand each finished record to ``record(cell, record)`` as it
    arrives; returns how many ran. A task that fails for a reason other than a lost worker
    raises here, after the records that did arrive were handed over."""
    from distributed import as_completed

    futures = {client.submit(cell_task, cell, repeat, matrix_name, run, pure=False,
                             key=f"cell-{cell.key}-{i}"): cell for i, cell in enumerate(cells)}
    ran = 0
    try:
        for future in as_completed(futures):
            record(futures[future], future.result())
            ran += 1
    finally:
        for future in futures:
            future.cancel()
    return ran

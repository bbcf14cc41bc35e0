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

import logging
import signal
from contextlib import contextmanager

from engine.core.errors import ConfigError, PacketrtError


class ClusterLost(PacketrtError):
    """The scheduler went away, or a task's workers kept dying, before every task finished:
    what finished is kept (``results.jsonl``), the rest can be run again with --resume."""


def _lost(error: BaseException) -> bool:
    """Whether ``error`` from a future says the cluster failed rather than the task's own code:
    the scheduler's connection lost (the futures cancelled), a task that killed its workers
    (distributed's KilledWorker), a closed comm."""
    from concurrent.futures import CancelledError

    names = {kind.__name__ for kind in type(error).__mro__}
    return isinstance(error, CancelledError) or bool(names & {"KilledWorker", "CommClosedError"})


def _why(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0] if text else ''}".rstrip(": ")


@contextmanager
def quiet_dask_logs():
    """distributed's own log lines held back while a command runs on a cluster: a lost scheduler
    or worker logged tracebacks of distributed's internals ("Failed to reconnect", "marked as
    failed") around the one error line that says what happened. The level comes back after."""
    logger = logging.getLogger("distributed")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(level)


@contextmanager
def _quiet_worker_processes():
    """Start local worker processes with Ctrl-C ignored and distributed logging only errors
    (both inherited by the processes started meanwhile): a terminal sends SIGINT to the whole
    process group, and each worker printed its own KeyboardInterrupt traceback, and a warning for
    the cell it was running, while the command itself stops them as it exits."""
    import os

    before = os.environ.get(WORKER_LOG_LEVEL)
    os.environ[WORKER_LOG_LEVEL] = "error"
    try:
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread: signals are not ours to set
        previous = None
    try:
        yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
        if before is None:
            os.environ.pop(WORKER_LOG_LEVEL, None)
        else:
            os.environ[WORKER_LOG_LEVEL] = before


#: Dask's configuration variable of distributed's log level, read by each worker as it starts.
WORKER_LOG_LEVEL = "DASK_LOGGING__DISTRIBUTED"
#: ``--scheduler`` with no address.
LOCAL = "local"
#: Seconds to wait for a first worker at a scheduler that has none.
WORKER_WAIT = 30.0


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
        with _quiet_worker_processes():
            # ":0": the scheduler's HTTP routes on a free port (with None it still took 8787, and
            # warned when another cluster held it).
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
        return Client(cluster), cluster
    try:
        # Dask's own connect timeout (distributed.comm.timeouts.connect, 30 s unless the user's
        # Dask config or DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT says otherwise).
        client = Client(address)
    except Exception as error:  # noqa: BLE001 -- any failure to connect (a refused or timed-out
        # address, a tls:// address without Dask's TLS settings, a ucx:// one without UCX) is
        # this one line, not a traceback of distributed's internals
        raise ConfigError(f"--scheduler {address}: cannot reach a Dask scheduler there "
                          f"({type(error).__name__}: {error})") from None
    try:
        # A scheduler without workers would take the tasks and wait for ever.
        client.wait_for_workers(1, timeout=WORKER_WAIT)
    except Exception:  # noqa: BLE001 -- distributed's TimeoutError, or the scheduler gone meanwhile
        client.close()
        raise ConfigError(f"--scheduler {address}: the scheduler has no workers (none joined in {WORKER_WAIT:g} s); "
                          f"start some with `dask worker {address}`") from None
    return client, None


def run_on_cluster(client, task, cells: list, record) -> int:
    """Submit ``task(cell)`` for every cell (a module-level function the workers import by
    name: ``engine.bench.runner.measure_cell_afresh`` with its other arguments bound), then hand
    each finished record to ``record(cell, record)`` as it arrives; returns how many ran. A task
    that fails for a reason other than a lost worker raises here, after the records that did
    arrive were handed over."""
    from distributed import as_completed

    futures = {client.submit(task, cell, pure=False, key=f"cell-{cell.key}-{i}"): cell
               for i, cell in enumerate(cells)}
    ran = 0
    try:
        for future in as_completed(futures):
            try:
                answer = future.result()
            except Exception as error:
                if not _lost(error):
                    raise  # the task's own error (a PacketrtError is one line)
                raise ClusterLost(f"the Dask cluster failed after {ran} of {len(cells)} cell(s) "
                                  f"({futures[future].describe()}: {_why(error)})") from None
            record(futures[future], answer)
            ran += 1
    finally:
        for future in futures:
            future.cancel()
    return ran


def audit_task(config, lo: int, hi: int, oracle: str) -> tuple:
    """On a worker: (report, image f32[H,W,3], mismatching pixels) of the band [lo, hi) of the
    config's frame (``validation.audit.audit_band``); the scene is loaded there."""
    from engine.core.numba_settings import hide_setup_warnings
    from scenes.catalog import scene_from_config
    from validation.audit import audit_band

    hide_setup_warnings()   # a worker is a process of its own: the command line's filters are not here
    scene = scene_from_config(config.scene, config.override)
    report, result, pixels = audit_band(scene, config, lo, hi, oracle)
    return report, result.image, list(pixels)


def audit_on_cluster(config, tiles: int, scheduler: str, workers: int = 1, oracle: str = "embree") -> tuple:
    """(merged report, image, mismatching pixels) of an audit split into ``tiles`` bands of
    rows, each a Dask task (every task renders the frame and checks only its band's rays, so the
    checking, the costly part on a large scene, spreads over the workers)."""
    from validation.audit import merge_reports

    rows = config.render.height
    if not 1 <= workers <= 256:
        raise ConfigError(f"--workers must be in 1..256, got {workers}")
    if not 1 <= tiles <= rows:   # more bands than rows made empty bands, silently dropped
        raise ConfigError(f"--tiles must be in 1..{rows:,} (the frame's rows: each band is whole rows), got {tiles}")
    edges = [config.render.width * (rows * k // tiles) for k in range(tiles + 1)]
    client, cluster = connect(scheduler, workers)
    with quiet_dask_logs():
        try:
            results = _audit_bands(client, config, edges, oracle)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    report = merge_reports([r for r, _, _ in results])
    return report, results[0][1], sorted(p for _, _, found in results for p in found)


def _audit_bands(client, config, edges: list, oracle: str) -> list:
    """``audit_on_cluster``'s tasks, one per band between consecutive ``edges`` (ray indices):
    [(report, image, pixels)] in band order."""
    futures = [client.submit(audit_task, config, lo, hi, oracle, pure=False) for lo, hi in zip(edges, edges[1:])]
    try:
        return [future.result() for future in futures]
    except Exception as error:
        if not _lost(error):
            raise
        raise ClusterLost(f"the Dask cluster failed during the audit ({_why(error)}); run it again") from None
    finally:
        client.cancel(futures)  # nothing left pending when the client closes (Ctrl-C included)

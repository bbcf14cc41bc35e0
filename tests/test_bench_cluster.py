"""``packetrt bench --scheduler``: the smoke matrix's cells as Dask tasks on a local cluster of
two worker processes give the serial runner's cells and answers; a worker killed mid-cell loses
no cell and records none twice."""
from __future__ import annotations

import functools
import json
from pathlib import Path

import pytest

pytest.importorskip("distributed")

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "benchmarks" / "smoke.toml"


def records(folder: Path) -> dict:
    return {r["id"]: r for r in map(json.loads, (folder / "results.jsonl").read_text().splitlines())}


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    from engine.bench.matrix import load_matrix
    from engine.bench.runner import run_matrix

    out = tmp_path_factory.mktemp("serial")
    run_matrix(load_matrix(str(SMOKE)), out, progress=False)
    return records(out)


@pytest.fixture(scope="module")
def two_workers():
    """The address of a local Dask cluster of two worker processes, started once for the module's
    runs, which reach it as an existing cluster (``--scheduler ADDRESS``): the workers' start-up
    (Python, numba, packetrt's kernels from the disk cache: about 6 s) is paid once. The
    ``--scheduler`` path without an address, which starts its own, is the tiled audit's below."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        yield cluster.scheduler_address


def test_two_workers_give_the_serial_runners_cells_and_answers(serial, two_workers, tmp_path):
    from engine.bench.matrix import load_matrix
    from engine.bench.runner import run_matrix

    summary = run_matrix(load_matrix(str(SMOKE)), tmp_path, progress=False, scheduler=two_workers, workers=2)
    assert summary["ran"] == len(serial) and summary["skipped"] == 0
    lines = (tmp_path / "results.jsonl").read_text().splitlines()
    clustered = records(tmp_path)
    assert len(lines) == len(clustered) == len(serial)
    assert set(clustered) == set(serial)
    for key, record in clustered.items():
        assert record["rays"] == serial[key]["rays"]
        assert record["checks"] == serial[key]["checks"]
        assert record["config"] == serial[key]["config"]
        assert record["machine"]["cpu"] and record["machine"]["numba_threads"] >= 1
    # --resume across schedulers: everything is done, the serial runner runs nothing more.
    assert run_matrix(load_matrix(str(SMOKE)), tmp_path, resume=True, progress=False)["ran"] == 0


def test_a_worker_lost_mid_cell_loses_no_cell_and_records_none_twice(serial, two_workers, tmp_path):
    from engine.bench.matrix import load_matrix
    from engine.bench.runner import run_matrix
    from tests.bench_cluster_helpers import crash_once_then_run

    marker = tmp_path / "crashed"
    out = tmp_path / "out"
    summary = run_matrix(load_matrix(str(SMOKE)), out, progress=False, scheduler=two_workers, workers=2,
                         run=functools.partial(crash_once_then_run, marker=str(marker)))
    assert marker.exists()  # a worker did die mid-cell
    ids = [json.loads(line)["id"] for line in (out / "results.jsonl").read_text().splitlines()]
    assert sorted(ids) == sorted(serial) and len(ids) == len(set(ids))
    assert summary["ran"] == len(serial)


def test_an_unreachable_scheduler_is_one_line(tmp_path, capsys):
    from engine.cli import main

    import dask

    out = tmp_path / "new"
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):  # Dask's own knob, 30 s by default
        assert main(["bench", str(SMOKE), "--out", str(out), "--scheduler", "tcp://127.0.0.1:9"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("packetrt: error: --scheduler tcp://127.0.0.1:9: cannot reach a Dask scheduler")
        assert not out.exists()  # the folder it made for the results is gone again, not left empty
        # A folder that was there stays, with what it held.
        out.mkdir()
        (out / "notes.txt").write_text("mine")
        assert main(["bench", str(SMOKE), "--out", str(out), "--scheduler", "tcp://127.0.0.1:9"]) == 2
        assert (out / "notes.txt").read_text() == "mine"


def test_a_tiled_audit_over_the_cluster_equals_the_serial_audit(tmp_path):
    """``packetrt audit --scheduler --tiles 3``: three bands of rows as tasks on two workers,
    merged into the report the serial audit writes (every ray checked once)."""
    from engine.cli import main

    common = ["audit", "--size", "40x30", "--param", "subdivisions=1"]
    assert main(common + ["--json", str(tmp_path / "serial.json")]) == 0
    assert main(common + ["--json", str(tmp_path / "tiled.json"), "--scheduler", "--workers", "2",
                          "--tiles", "3"]) == 0
    serial, tiled = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("serial", "tiled"))
    assert tiled["bands"] == [[0, 400], [400, 800], [800, 1200]]
    assert tiled["by_kind"] == serial["by_kind"] and tiled["rays_checked"] == serial["rays_checked"] > 1200
    assert tiled["mismatch_count"] == serial["mismatch_count"] == 0


@pytest.mark.parametrize("extra, message", [
    (["--workers", "0"], "--workers must be in 1..256, got 0"),
    (["--tiles", "0"], "--tiles must be in 1..16 (the frame's rows: each band is whole rows), got 0"),
    # More bands than rows: some bands were empty and silently dropped.
    (["--tiles", "17"], "--tiles must be in 1..16 (the frame's rows: each band is whole rows), got 17")])
def test_zero_workers_or_tiles_are_refused_not_defaulted(extra, message, capsys):
    from engine.cli import main

    assert main(["audit", "--size", "16x16", "--scheduler"] + extra) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == f"packetrt: error: {message}"


def test_workers_print_no_warning_about_numbas_set_up(capfd):
    """A worker is a process of its own: the command line's warning filters did not reach it,
    and with Open3D loaded (its TBB is older than numba's TBB layer wants) every worker printed
    numba's TBB note into the audit's output."""
    from engine.cli import main

    assert main(["audit", "--size", "16x16", "--scheduler", "--oracle", "open3d"]) == 0
    out, err = capfd.readouterr()
    assert "audit whitted" in out
    assert "TBB threading layer" not in err and "NumbaWarning" not in err


@pytest.mark.parametrize("address", ["tls://127.0.0.1:9", "ucx://127.0.0.1:9"])
def test_a_scheduler_address_distributed_cannot_use_is_one_line(address, tmp_path, capsys):
    """A tls:// address without Dask's TLS settings, or ucx:// without UCX: distributed raises
    a TypeError, which came out as a 50-line traceback and exit code 1."""
    from engine.cli import main

    assert main(["bench", str(SMOKE), "--out", str(tmp_path / "o"), "--scheduler", address]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"packetrt: error: --scheduler {address}: cannot reach a Dask scheduler")
    assert not any(line.startswith("Traceback") for line in err)


def test_a_cell_that_keeps_killing_its_worker_is_one_error_and_the_rest_is_kept(tmp_path):
    """Dask gives up on a task whose workers keep dying (KilledWorker; a lost scheduler cancels
    the futures the same way): that was a traceback of distributed's, exit 1, and no tables for
    the cells that had finished. Now one PacketrtError naming the cell, the finished records
    whole, the tables written for them."""
    import dask

    from engine.bench.cluster import LOCAL, ClusterLost
    from engine.bench.matrix import load_matrix
    from engine.bench.runner import run_matrix
    from tests.bench_cluster_helpers import crash_on_cell

    matrix = load_matrix(str(SMOKE))
    doomed = matrix.cells[-1]
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):  # the first death gives up
        with pytest.raises(ClusterLost, match="KilledWorker") as caught:
            run_matrix(matrix, tmp_path, progress=False, scheduler=LOCAL, workers=1,
                       run=functools.partial(crash_on_cell, key=doomed.key))
    assert doomed.describe() in str(caught.value) and "\n" not in str(caught.value)
    kept = records(tmp_path)
    assert doomed.key not in kept
    assert (tmp_path / "results.jsonl").read_text().endswith("\n") or not kept
    assert (tmp_path / "results.csv").is_file() == bool(kept)


def test_a_lost_cluster_error_is_told_from_the_tasks_own():
    from concurrent.futures import CancelledError

    from engine.bench.cluster import _lost

    class KilledWorker(Exception):  # distributed.scheduler's, by name
        pass

    assert _lost(CancelledError("scheduler-connection-lost")) and _lost(KilledWorker("task"))
    assert not _lost(ValueError("the task's own")) and not _lost(OSError("a file the task read"))


def test_a_scheduler_without_workers_is_one_line_not_a_wait_for_ever(tmp_path, capsys, monkeypatch):
    from distributed import LocalCluster

    from engine.bench import cluster
    from engine.cli import main

    monkeypatch.setattr(cluster, "WORKER_WAIT", 1.0)
    with LocalCluster(n_workers=0, processes=False, dashboard_address=":0") as empty:
        address = empty.scheduler_address
        assert main(["bench", str(SMOKE), "--out", str(tmp_path / "o"), "--scheduler", address]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (f"packetrt: error: --scheduler {address}: the scheduler has no workers (none joined in 1 s); "
                       f"start some with `dask worker {address}`")
    assert not (tmp_path / "o").exists()


def test_workers_with_a_scheduler_address_is_refused_not_ignored(tmp_path, capsys):
    from engine.cli import main

    assert main(["bench", str(SMOKE), "--out", str(tmp_path / "o"), "--scheduler", "tcp://127.0.0.1:9",
                 "--workers", "4"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("packetrt: error: --workers sizes the local Dask cluster") and "tcp://127.0.0.1:9" in err[-1]

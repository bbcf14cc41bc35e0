"""``packetrt bench MATRIX.toml [--out DIR] [--repeat N] [--resume]``: the batch benchmark runner.

Each cell of the matrix (``engine.bench.matrix``) is measured in this process, one after another:

1. a warm-up render that absorbs JIT compilation and records every ray batch the Whitted loop
   casts (kind, query, rays, packets) through the renderer's ``observer`` hook;
2. ``repeat`` timed renders: frame time (shading included), per-kind trace time, shading time;
3. ``repeat`` replays of the recorded batches through the renderer's own ``Tracer`` (timed as
   the render times them: frustum build + query + answer arrays), then, when every
   ray kind uses a packet traversal, ``repeat`` replays of the per-ray floor
   (``engine.bench.floor``: the same with the BVH walk taken out), then Embree (the ``embree``
   traversal, same thread count) and Open3D's ``RaycastingScene`` (``engine.bench.open3d_yardstick``,
   same thread count) on exactly the same batches: the ratios to either yardstick compare the
   same rays, the same work, minutes apart at most;
   Every timed variant keeps the answers of its last replay, and they are checked against the
   reference answers of the same batches (the ``single`` traversal, once per batch set) by the
   audit's tie-aware rules: a variant that disagrees on a ray kind is reported on stderr, its
   rates for that kind are dropped (None) and ``checks`` in the record says how many rays
   (Open3D, which promises no watertightness, keeps its rates below a small tolerance of
   disagreeing rays and is flagged instead: ``engine.bench.open3d_yardstick.open3d_rates``);
4. one counting render for the counters (ray-AABB and ray-triangle tests, per BVH depth) and
   the plugins' own statistics (e.g. the ray-space hierarchy's candidates per ray).

Timings are kept as median, min, max and quartiles over the repeats. A finished cell is
appended to ``DIR/results.jsonl`` at once (see ``engine.bench.results``); ``--resume`` skips
cells already there; Ctrl-C stops between two writes, rewrites the CSV, tables and plots for
what is finished, and the same command with ``--resume`` carries on.

Embree's and Open3D's times on a set of batches do not depend on our traversal, so within one
run each is measured once per distinct batch set (same scene, recursion, size and packet order,
checked by a digest of the rays) and shared by the cells that trace it (``EmbreeYardstick``,
``Open3DYardstick``).
"""
from __future__ import annotations

import datetime
import functools
import hashlib
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from engine.bench import host_speed, paired_frames
from engine.bench import results as results_io
from engine.bench.floor import floor_tracer, uses_packet_traversals
from engine.bench.machine import machine_info
from engine.bench.cell_scenes import SceneCache, cell_scene
from engine.bench.cluster import LOCAL, ClusterLost
from engine.bench.matrix import MAX_REPEAT, Cell, Matrix, check_matrix_name, load_matrix
from engine.bench.open3d_yardstick import Open3DYardstick, open3d_rates, require_open3d
from engine.bench.yardstick import replay_once
from engine.core.atomic import output_file, output_folder, remove_if_empty
from engine.core.errors import ConfigError, PacketrtError
from engine.core.threads import numba_threads
from engine.core.types import RAY_KINDS, copied_batch, empty_hits
from engine.render.config import read_toml
from engine.render.plugins import make_traversal
from engine.render.tracer import Tally

#: The kinds of matrix besides one of cells (no ``kind``): each has its own runner.
MATRIX_KINDS = ("gpu", "dynamic", "trimesh")


# -- measurements --------------------------------------------------------------------------

def summarize(values) -> dict:
    """{median, min, max, q1, q3, runs} of a list of seconds."""
    a = np.asarray(values, np.float64)
    q1, median, q3 = np.percentile(a, [25, 50, 75])
    return {"median": float(median), "min": float(a.min()), "max": float(a.max()),
            "q1": float(q1), "q3": float(q3), "runs": [float(v) for v in a]}


class BatchRecorder:
    """Renderer observer that keeps every cast batch: list of (kind, query, RayBatch, Packets),
    and beside it ``from_end``: per batch, the end the renderer walks such a batch from (True:
    a shadow batch walked from the light, ``engine.render.shadow_order``), for ``replay``.

    Each batch is copied as it is handed over: the renderer reuses its per-lane arrays within a
    frame (a shadow batch's arrays serve every light and generation, a generation's the one two
    after it), so views kept until the frame ends hold later batches' rays, not these."""

    wants_walk_order = True

    def __init__(self):
        self.batches = []
        self.from_end = []

    def __call__(self, kind, query, rays, packets, answer, from_end=False):
        self.batches.append((kind, query, *copied_batch(rays, packets)))
        self.from_end.append(from_end)

    def digest(self, tris) -> str:
        """blake2b over the triangles ``tris`` the batches were traced against and every batch's
        query, rays (origins, directions, segments) and packet offsets. The triangles count: two
        scenes under one camera cast the same primary rays, and the second cell took the first's
        reference answers (its right answers called wrong) and yardstick timings."""
        h = hashlib.blake2b(digest_size=16)
        for array in (tris.v0, tris.v1, tris.v2):
            h.update(np.ascontiguousarray(array).data)
        for kind, query, rays, packets in self.batches:
            h.update(f"{kind}:{query}:{rays.org.shape[0]}".encode())
            for array in (rays.org, rays.dir, rays.tmin, rays.tmax, packets.offsets):
                h.update(np.ascontiguousarray(array).data)
        return h.hexdigest()



def answer_arrays(batches) -> list:
    """One answer per recorded batch, to trace into replay after replay: Hits (all misses) for
    an intersect batch, bool[R] for an occlusion batch, every page already written.

    A frame answers into arrays its renderer keeps (``engine.core.scratch``). Replays that made
    new answer arrays inside the timing paid their first-touch page faults there, by an amount
    that depended on what the allocator had freed before: a kitchen-paper frame's batches
    replayed by one tracer took 181.4 ms with new arrays and 172.1 ms with kept ones (2 threads,
    medians of 15, alternating; session 32), and in ``tools/fit_auto.py``'s replays the same
    compiled Ranged walk read 5% faster as ``auto`` than as ``ranged`` on the kitchen."""
    answers = []
    for _, query, rays, _ in batches:
        n = rays.org.shape[0]
        if query == "intersect":
            answers.append(empty_hits(n))  # np.full writes every page
        else:
            flags = np.empty(n, np.bool_)
            flags.fill(False)  # np.zeros may map untouched zero pages
            answers.append(flags)
    return answers


def replay(batches, tracer, from_end=None, answers=None) -> tuple:
    """({kind: seconds}, answers) of tracing the recorded batches again with ``tracer``, each
    batch timed by the tracer as a render times it (frustum build + query); answers[i] is batch
    i's Hits or bool[R], traced into ``answers`` (``answer_arrays``) when given, else into new
    arrays made inside the timing. from_end: per batch, the end to walk an occlusion batch from
    (``BatchRecorder.from_end``; None: the usual order)."""
    tally = Tally()
    ends = from_end if from_end is not None else [False] * len(batches)
    into = answers if answers is not None else [None] * len(batches)
    answers = [tracer.trace(kind, query, rays, packets, tally, answer, from_end=end)
               for (kind, query, rays, packets), end, answer in zip(batches, ends, into)]
    return tally.seconds, answers


def timed_replays(batches, tracer, repeat: int, from_end=None) -> tuple:
    """([{kind: seconds}] of ``repeat`` replays, the last replay's answers), every replay
    answering into the same arrays (``answer_arrays``, made before the first), as frames do."""
    seconds, answers = [], answer_arrays(batches)
    for _ in range(repeat):
        run, answers = replay(batches, tracer, from_end, answers)
        seconds.append(run)
    return seconds, answers


class ReferenceAnswers:
    """The reference answers of a recorded batch set: the ``single`` traversal (audited against
    Embree), closest hits for every batch (occlusion batches too: a differing occlusion answer is
    judged by where the hits lie). Computed once per distinct batch set, by digest."""

    def __init__(self):
        self.digest, self.closest = None, None

    def get(self, renderer, recorder: BatchRecorder) -> list:
        digest = recorder.digest(renderer.tris)
        if digest != self.digest:
            self.closest = None
            tracer = renderer.tracer.with_traversal(dict.fromkeys(RAY_KINDS, make_traversal("single")),
                                                    dict.fromkeys(RAY_KINDS))
            self.closest = [tracer.trace(kind, "intersect", rays, packets)
                            for kind, _, rays, packets in recorder.batches]
            self.digest = digest
        return self.closest


def check_answers(batches, answers, reference: list, tracer, tris) -> dict:
    """{kind: {"checked", "ties", "mismatches"}} of a timed variant's ``answers`` against the
    ``reference`` closest hits of the same batches, by the audit's tie-aware rules
    (``validation.compare``). For occlusion batches whose answers differ, the variant's own
    closest hits (``tracer``, untimed) say whether the difference is a graze."""
    from validation.compare import compare_hits, compare_occlusion

    out = {k: {"checked": 0, "ties": 0, "mismatches": 0} for k in RAY_KINDS}
    for (kind, query, rays, packets), answer, ref in zip(batches, answers, reference):
        if query == "intersect":
            result = compare_hits(rays, answer, ref, tris)
        else:
            ref_occluded = ref.prim >= 0
            differ = (answer != ref_occluded) & (rays.tmin <= rays.tmax)
            closest = tracer.trace(kind, "intersect", rays, packets) if differ.any() else ref
            result = compare_occlusion(rays, answer, ref_occluded, tris, closest, ref)
        row = out[kind]
        row["checked"] += int(np.count_nonzero(rays.tmin <= rays.tmax))
        row["ties"] += int(result.tie.sum())
        row["mismatches"] += int(result.mismatch.sum())
    return out


class EmbreeYardstick:
    """Embree's seconds on a recorded batch set, measured once per distinct set (by digest), and
    the Embree scenes used, closed at the end: an Embree thread-pool worker that Ctrl-C caught
    half-registered (CPython starts it, then records it for the exit handler) would otherwise
    keep the interpreter from exiting; closing the pool wakes and ends every worker."""

    def __init__(self):
        self.digest, self.runs, self.answers, self.scenes = None, None, None, {}
        self.plugin = None  # one Embree plugin for the run: its scene is reused across cells

    def note(self, renderer) -> None:
        """Remember the Embree scenes a cell's renderer used (built once, closed at the end)."""
        for plugin in renderer.traversal.values():
            if plugin.name == "embree":
                scene = plugin.scene_for(renderer.tris)
                self.scenes[id(scene)] = scene

    def tracer(self, renderer):
        """The renderer's BVH and triangles traced by Embree for every kind (no frusta)."""
        if self.plugin is None:
            self.plugin = make_traversal("embree")
        scene = self.plugin.scene_for(renderer.tris)  # built outside the timing
        self.scenes[id(scene)] = scene
        return renderer.tracer.with_traversal(dict.fromkeys(RAY_KINDS, self.plugin), dict.fromkeys(RAY_KINDS))

    def seconds(self, renderer, recorder: BatchRecorder, repeat: int) -> tuple:
        """(``repeat`` dicts {kind: seconds}, last answers) of Embree on exactly the recorded batches."""
        return replay_once(self, renderer, recorder, repeat, timed_replays)

    def close(self) -> None:
        for scene in self.scenes.values():
            scene.close()
        self.scenes.clear()


def _checked(rates: dict, check: dict) -> dict:
    """``rates`` with the kinds whose answers mismatched the reference set to None (a wrong
    answer's speed is not a result), and "all" too when any kind did."""
    bad = [k for k in RAY_KINDS if check[k]["mismatches"]]
    return {k: (None if k in bad or (k == "all" and bad) else v) for k, v in rates.items()}


def _report_mismatches(cell: Cell, checks: dict, kept: dict | None = None) -> None:
    """One stderr line per variant whose answers disagree; ``kept``: {variant: rates} of a
    variant whose rates survive a few mismatches (Open3D), to say which were kept."""
    for variant, check in checks.items():
        bad = {k: row["mismatches"] for k, row in check.items() if row["mismatches"]}
        if bad:
            rates = (kept or {}).get(variant)
            fate = ("those rates are dropped" if rates is None else
                    f"rates kept (flagged) for {[k for k in bad if rates.get(k) is not None]}, dropped for "
                    f"{[k for k in bad if rates.get(k) is None]}")
            print(f"packetrt bench: {cell.describe()}: {variant} answers disagree with the reference "
                  f"(single) on {bad} rays; {fate}", file=sys.stderr)


def _rates(rays: dict, seconds: dict) -> dict:
    """Mrays/s per kind (None where no rays) and over all kinds."""
    rates = {k: (rays[k] / seconds[k] / 1e6 if rays[k] and seconds[k] > 0 else None) for k in RAY_KINDS}
    total = sum(seconds[k] for k in RAY_KINDS if rays[k])
    rates["all"] = rays["all"] / total / 1e6 if total > 0 else None
    return rates


# -- one cell --------------------------------------------------------------------------------

def run_cell(cell: Cell, repeat: int, scene_cache: SceneCache, yardstick: EmbreeYardstick, machine: dict,
             matrix_name: str, references: ReferenceAnswers | None = None,
             open3d: Open3DYardstick | None = None) -> dict:
    """Measure one cell (see the module doc); returns its results.jsonl record. Its frames, replays
    and yardsticks all run at the cell's thread count; the caller's count is back afterwards. The
    host's speed is probed just before and after (``engine.bench.host_speed``), into "host"."""
    with numba_threads(cell.config().render.threads):
        before = host_speed.measure()
        record = _measure_cell(cell, repeat, scene_cache, yardstick, machine, matrix_name, references, open3d)
        record["host"] = {"before": before, "after": host_speed.measure()}
        return record


def _measure_cell(cell, repeat, scene_cache, yardstick, machine, matrix_name, references, open3d) -> dict:
    from engine.render.whitted import WhittedRenderer

    references = references or ReferenceAnswers()
    open3d = open3d or Open3DYardstick()

    wall = time.perf_counter()
    started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    load_at_start = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    scene = cell_scene(scene_cache.get(cell.scene), cell)
    config = cell.config()
    recorder = BatchRecorder()
    renderer = WhittedRenderer(scene, config, observer=recorder)
    warm = renderer.render()  # JIT compilation happens here, untimed
    # Only the measurements are kept: an image kept alive per frame (12 MiB at 1024x1024) made
    # every timed frame's image fresh memory, whose page faults landed in the shading passes
    # (15-25 ms a kitchen frame) in a process's first cell but not in later ones, whose images
    # reused memory the earlier cells had freed.
    warm.image = None
    renderer.observer = None
    frames = [renderer.render().seconds for _ in range(repeat)]

    # Our share of the CPU while replaying: near 1 on an idle machine (parallel kernels keep
    # every thread busy), well below when other work competes for the cores.
    cpu, clock = time.process_time(), time.perf_counter()
    replays, answers = timed_replays(recorder.batches, renderer.tracer, repeat, recorder.from_end)
    cpu_share = (time.process_time() - cpu) / max((time.perf_counter() - clock) * renderer.threads, 1e-9)
    reference = references.get(renderer, recorder)
    checks = {"ours": check_answers(recorder.batches, answers, reference, renderer.tracer, renderer.tris)}
    answers = None
    # The packet traversals' per-ray floor on the same batches (engine.bench.floor): the part
    # of the trace time no traversal can remove. It answers "no hit" by design: not checked.
    floors = None
    if uses_packet_traversals(renderer):
        floor = floor_tracer(renderer)
        replay(recorder.batches, floor)  # untimed: JIT and first touch
        floors, _ = timed_replays(recorder.batches, floor, repeat)
    if "embree" in cell.traversal.names:
        yardstick.note(renderer)
    embree_seconds = None
    if cell.embree:
        if set(cell.traversal.names) == {"embree"}:
            embree_seconds = replays  # the cell is Embree: its replay is the yardstick
            checks["embree"] = checks["ours"]
        else:
            embree_seconds, embree_answers = yardstick.seconds(renderer, recorder, repeat)
            checks["embree"] = check_answers(recorder.batches, embree_answers, reference,
                                             yardstick.tracer(renderer), renderer.tris)
            embree_answers = None
    open3d_seconds = None
    if cell.open3d:
        open3d_seconds, open3d_answers = open3d.seconds(renderer, recorder, repeat, timed_replays)
        checks["open3d"] = check_answers(recorder.batches, open3d_answers, reference, open3d.tracer(renderer),
                                         renderer.tris)
        open3d_answers = None

    counted = renderer.with_counters(renderer.render())

    rays = dict(warm.rays)
    rays["all"] = sum(warm.rays[k] for k in RAY_KINDS)
    batches = {k: sum(1 for b in recorder.batches if b[0] == k) for k in RAY_KINDS}
    packets = {k: sum(len(b[3].offsets) - 1 for b in recorder.batches if b[0] == k) for k in RAY_KINDS}
    replay_summary = {k: summarize([r[k] for r in replays]) for k in RAY_KINDS}
    replay_median = {k: replay_summary[k]["median"] for k in RAY_KINDS}
    mrays = _checked(_rates(rays, replay_median), checks["ours"])
    embree_summary = embree_mrays = ratio = None
    embree_fps = None
    if embree_seconds is not None:
        embree_summary = {k: summarize([r[k] for r in embree_seconds]) for k in RAY_KINDS}
        embree_mrays = _checked(_rates(rays, {k: embree_summary[k]["median"] for k in RAY_KINDS}),
                                checks["embree"])
        ratio = {k: (mrays[k] / embree_mrays[k] if mrays[k] and embree_mrays[k] else None) for k in mrays}
        total = sum(embree_summary[k]["median"] for k in RAY_KINDS)
        embree_fps = 1.0 / total if total > 0 else None
    open3d_summary = open3d_mrays = open3d_ratio = open3d_fps = None
    if open3d_seconds is not None:
        open3d_summary = {k: summarize([r[k] for r in open3d_seconds]) for k in RAY_KINDS}
        open3d_mrays = open3d_rates(_rates(rays, {k: open3d_summary[k]["median"] for k in RAY_KINDS}),
                                    checks["open3d"])
        open3d_ratio = {k: (mrays[k] / open3d_mrays[k] if mrays[k] and open3d_mrays[k] else None) for k in mrays}
        total = sum(open3d_summary[k]["median"] for k in RAY_KINDS)
        open3d_fps = 1.0 / total if total > 0 else None
    _report_mismatches(cell, checks, kept={"open3d": open3d_mrays} if open3d_mrays else None)
    frame = summarize([f["total"] for f in frames])
    trace_total = sum(replay_median.values())
    record = {
        "schema": results_io.SCHEMA, "id": cell.key, "matrix": matrix_name, "tags": list(cell.tags),
        "labels": cell.labels(), "cell": cell.identity(), "config": config.to_dict(),
        "scene": {"name": scene.name, "triangles": scene.n_triangles, "lights": len(scene.lights)},
        "repeat": repeat, "threads": renderer.threads,
        "seconds": {"bvh": warm.seconds["bvh"], "plugin_build": warm.seconds["plugin_build"], "frame": frame,
                    "shade": summarize([f["shade"] for f in frames]),
                    "trace": {k: summarize([f["trace"][k] for f in frames]) for k in RAY_KINDS},
                    "replay": replay_summary, "embree": embree_summary, "open3d": open3d_summary,
                    "floor": None if floors is None else {k: summarize([f[k] for f in floors]) for k in RAY_KINDS}},
        "rays": rays, "batches": batches, "packets": packets, "mrays_per_s": mrays, "embree_mrays_per_s": embree_mrays,
        "ratio_to_embree": ratio, "open3d_mrays_per_s": open3d_mrays, "ratio_to_open3d": open3d_ratio,
        "checks": checks,
        "fps": {"frame": 1.0 / frame["median"] if frame["median"] > 0 else None,
                "trace": 1.0 / trace_total if trace_total > 0 else None, "embree_trace": embree_fps,
                "open3d_trace": open3d_fps},
        "counters": counted.counters, "counters_by_depth": counted.counters_by_depth, "extra": counted.extra,
        "machine": machine, "started": started,
        "load": {"loadavg_at_start": load_at_start, "cpu_share_replay": cpu_share},
    }
    record["wall_seconds"] = time.perf_counter() - wall
    return record


# -- the matrix ------------------------------------------------------------------------------

def _cost(cell: Cell, scene: tuple, repeat: int) -> float:
    """Rough relative cost of a cell for the ETA: rays cast times passes over them, times a
    slowness guess per traversal (measured here: the ray-space hierarchy's cost grows with the
    triangle count, a BVH's barely). ``scene`` = (lights, triangles)."""
    lights, triangles = scene
    if cell.preset.max_lights is not None:  # the preset keeps only the first lights
        lights = min(lights, cell.preset.max_lights)
    kinds = 1 + (lights if cell.preset.lights else 0)
    generations = 1 + cell.preset.max_depth
    slow = 3.0 if cell.packet <= 2 or "single" in cell.traversal.names else 1.0
    if "rayspace" in cell.traversal.names:
        slow = max(slow, triangles / 1000)
    return cell.width * cell.height * kinds * generations * slow * (2 + 3 * repeat) / 1e6


def preflight(cells, source: str = "<matrix>") -> dict:
    """Load every distinct scene once before any measurement (a loader's own parameter checks
    fail here, not halfway through, as one error naming the matrix file ``source`` and the
    scene): {(name, params, time): (lights, triangles)}."""
    from scenes.catalog import load_named

    found = {}
    for cell in cells:
        key = (cell.scene.name, cell.scene.params, cell.scene.time)
        if key not in found:
            try:
                scene = load_named(cell.scene.name, dict(cell.scene.params), cell.scene.time)
            except PacketrtError as exc:
                params = ", ".join(f"{k} = {v!r}" for k, v in cell.scene.params)
                raise type(exc)(f"{source}: scene {cell.scene.name!r}"
                                f"{' (' + params + ')' if params else ''}: {exc}") from None
            found[key] = (len(scene.lights), scene.n_triangles)
    return found


def write_outputs(out: Path, matrix: Matrix) -> list:
    """results.csv, tables and plots from results.jsonl (the cells of this matrix that are done)."""
    from engine.bench.plots import render_plots

    records, _ = results_io.read_results(out / results_io.RESULTS)
    tags = {c.key: list(c.tags) for c in matrix.cells}
    order = {c.key: i for i, c in enumerate(matrix.cells)}
    mine = sorted((dict(r, tags=tags[r["id"]]) for r in records if r["id"] in tags), key=lambda r: order[r["id"]])
    results_io.write_csv(out / results_io.CSV, mine)
    return [out / results_io.CSV] + render_plots(mine, out, matrix.plots)


def _is_interrupt(exc: BaseException) -> bool:
    """A KeyboardInterrupt, or what numba makes of one: Ctrl-C during a compiled call surfaces
    as "SystemError: CPUDispatcher(...) returned a result with an exception set", caused by it."""
    while exc is not None:
        if isinstance(exc, KeyboardInterrupt):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def measure_cell_afresh(cell: Cell, repeat: int, matrix_name: str, run=None) -> dict:
    """One cell measured with fresh caches and yardsticks and this process's machine in its
    record (``run``: the measuring function, default ``run_cell``): a Dask worker's task."""
    from engine.core.numba_settings import hide_setup_warnings

    hide_setup_warnings()   # a worker is a process of its own: the command line's filters are not here
    run = run or run_cell
    yardstick, open3d = EmbreeYardstick(), Open3DYardstick()
    try:
        return run(cell, repeat, SceneCache(), yardstick, machine_info(), matrix_name, ReferenceAnswers(),
                   open3d=open3d)
    finally:
        yardstick.close()
        open3d.close()


def _check_same_matrix(records: list, matrix: Matrix, path: Path) -> None:
    """--resume goes on with the same matrix at the same --repeat: records of another matrix
    (or repeat count) in ``path`` were counted as done and their cells silently kept."""
    other = [r for r in records if r.get("matrix", matrix.name) != matrix.name
             or r.get("repeat", matrix.repeat) != matrix.repeat]
    if other:
        first = other[0]
        raise ConfigError(f"--resume: {path} holds {len(other)} record(s) of matrix {first.get('matrix')!r} with "
                          f"repeat {first.get('repeat')}; this run is {matrix.name!r} with repeat {matrix.repeat} "
                          f"(give another --out, or leave out --resume to start afresh)")


def _run_on_dask(matrix: Matrix, todo: list, path: Path, scheduler: str, workers: int, run, recorded) -> int:
    """The cells ``todo`` as Dask tasks, each record appended to ``path`` as it arrives and
    counted in ``recorded`` (a list, one entry a record: the count survives an interrupt)."""
    from engine.bench.cluster import connect, quiet_dask_logs, run_on_cluster

    client, cluster = connect(scheduler, workers)
    print(f"{matrix.name}: {len(todo)} cell(s) as Dask tasks on {client.scheduler.address} "
          f"({len(client.scheduler_info()['workers'])} worker(s))", file=sys.stderr)

    def record(cell, record):
        results_io.append(path, record)
        recorded.append(cell.key)

    with quiet_dask_logs():
        try:
            task = functools.partial(measure_cell_afresh, repeat=matrix.repeat, matrix_name=matrix.name, run=run)
            return run_on_cluster(client, task, todo, record)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()


def steadiest(measure, record: dict, limit: float, retries: int, fastest: dict):
    """(record, fastest): ``record``, or a measurement of the same cell again (``measure()``, at
    most ``retries`` more) when the host ran more than ``limit`` times slower around it than
    ``fastest`` (the fastest host probes of the run so far, ``results.fastest_host``) -- the one
    whose host ran fastest is kept, with host["measured"], how many times the cell was measured.
    ``fastest`` comes back with every probe seen folded in."""
    best, measured = record, 1
    fastest = results_io.fastest_host([record], fastest)
    slowness = results_io.host_slowness(best, fastest)
    while slowness is not None and slowness > limit and measured <= retries:
        again = measure()
        measured += 1
        fastest = results_io.fastest_host([again], fastest)
        if results_io.host_slowness(again, fastest) < results_io.host_slowness(best, fastest):
            best = again
        slowness = results_io.host_slowness(best, fastest)
    if best.get("host"):
        best["host"]["measured"] = measured
    return best, fastest


def run_matrix(matrix: Matrix, out: Path, resume: bool = False, progress: bool = True, run=None,
               scheduler: str | None = None, workers: int = 1, steady: float | None = None,
               retries: int = 2) -> dict:
    """Run every cell not yet in ``out/results.jsonl``; {"ran", "skipped", "files"}.

    ``run`` measures one cell (default ``run_cell``, looked up at call time). A KeyboardInterrupt
    stops between cells (a cell in flight is dropped), the outputs are rewritten for what is
    done, and the interrupt is raised again. ``scheduler``: None runs the cells here, one after
    another; an address, or ``engine.bench.cluster.LOCAL`` for a local cluster of ``workers``
    processes, runs them as Dask tasks (``engine.bench.cluster``). ``steady``: measure a cell again,
    up to ``retries`` times, while the host runs more than ``steady`` times slower around it than
    at the run's fastest moment (``steadiest``; here only, not on a cluster).
    """
    created = not Path(out).exists()
    try:
        return _run_matrix(matrix, Path(out), resume, progress, run or run_cell, scheduler, workers, steady, retries)
    except BaseException:
        if created:  # an unreachable scheduler, a bad scene ...: no empty folder left behind
            remove_if_empty(Path(out))
        raise


def _run_matrix(matrix: Matrix, out: Path, resume: bool, progress: bool, run, scheduler: str | None, workers: int,
                steady: float | None, retries: int) -> dict:
    """``run_matrix``'s work, in a folder it may have created (which it removes when this fails
    before writing anything)."""
    from tqdm import tqdm

    output_folder(out, "--out")
    path = out / results_io.RESULTS
    output_file(path, "--out")  # a folder in its place is one line now, not after the first cell
    if resume:
        skipped, torn = results_io.skipped_lines(path)
        if skipped or torn:
            lines = ", ".join(map(str, skipped[:10])) + (" ..." if len(skipped) > 10 else "")
            print(f"packetrt bench: warning: {path}: " + "; ".join(
                  ([f"{len(skipped)} unreadable line(s) skipped (line {lines})"] if skipped else [])
                  + ([f"a torn last line of {torn} bytes cut off"] if torn else []))
                  + "; their cells are measured again", file=sys.stderr)
        results_io.repair(path)
    elif path.is_file() and path.stat().st_size:
        backup = results_io.free_backup_name(path)
        os.replace(path, backup)
        print(f"packetrt bench: starting afresh; earlier results moved to {backup} (--resume keeps them)",
              file=sys.stderr)
        for stale in paired_frames.PAIRED_FILES:  # the earlier run's pairs: this run writes its own, or none
            (out / stale).unlink(missing_ok=True)
    earlier = results_io.read_results(path)[0]
    if resume:
        _check_same_matrix(earlier, matrix, path)
    done = {r["id"] for r in earlier}
    todo = [c for c in matrix.cells if c.key not in done]
    scenes = preflight(todo, matrix.source) if todo else {}  # a bad scene parameter: one line, before any
    print(f"{matrix.name}: {len(matrix.cells)} cells, {len(matrix.cells) - len(todo)} already done, "
          f"{len(todo)} to run, {matrix.repeat} repeats -> {out}", file=sys.stderr)
    ran, interrupted = 0, False
    try:
        if todo:
            if any(c.open3d for c in todo):
                require_open3d(matrix.source)
            here = todo
            if scheduler is not None:
                recorded = []
                try:
                    ran = _run_on_dask(matrix, todo, path, scheduler, workers, run if run is not run_cell else None,
                                       recorded)
                finally:
                    ran = len(recorded)
                here = []
            machine = machine_info()
            costs = [_cost(c, scenes[(c.scene.name, c.scene.params, c.scene.time)], matrix.repeat) for c in here]
            scene_cache, yardstick, references = SceneCache(), EmbreeYardstick(), ReferenceAnswers()
            open3d = Open3DYardstick()
            fastest = results_io.fastest_host([{"host": {"before": host_speed.measure()}}]) \
                if steady is not None else {}
            bar = tqdm(total=sum(costs), disable=not progress or not here, file=sys.stderr, dynamic_ncols=True,
                       bar_format="{l_bar}{bar}| {postfix} [{elapsed}<{remaining}]")
            try:
                for i, (cell, cost) in enumerate(zip(here, costs)):
                    bar.set_postfix_str(f"cell {i + 1}/{len(here)}: {cell.describe()}")
                    def measure(cell=cell):
                        return run(cell, matrix.repeat, scene_cache, yardstick, machine, matrix.name, references,
                                   open3d=open3d)
                    record = measure()
                    if steady is not None:
                        record, fastest = steadiest(measure, record, steady, retries, fastest)
                    results_io.append(path, record)
                    ran += 1
                    bar.update(cost)
            finally:
                bar.close()
                yardstick.close()
                open3d.close()
        if matrix.paired:
            if scheduler is None:
                paired_frames.run_paired(matrix, out)
            else:
                print("packetrt bench: [paired] frames are rendered here, one process for all variants; "
                      "skipped with --scheduler", file=sys.stderr)
    except (KeyboardInterrupt, SystemError) as exc:
        if not _is_interrupt(exc):
            raise
        interrupted = True
    except ClusterLost:
        if ran:  # the finished cells' tables, as after an interrupt; the error is the one line
            write_outputs(out, matrix)
        raise
    if interrupted and not results_io.read_results(path)[0]:
        # Stopped before any cell finished: no empty tables (and a folder this run made goes).
        print("packetrt bench: interrupted before the first cell finished", file=sys.stderr)
        raise KeyboardInterrupt
    files = write_outputs(out, matrix)
    files += [out / name for name in paired_frames.PAIRED_FILES if matrix.paired and (out / name).is_file()]
    if interrupted:
        print(f"packetrt bench: interrupted after {ran} new cell(s); {out / results_io.RESULTS} holds every "
              f"finished cell; run again with --resume to finish", file=sys.stderr)
        raise KeyboardInterrupt
    return {"ran": ran, "skipped": len(matrix.cells) - len(todo), "files": files}


def cmd_bench(args) -> int:
    """The CLI entry: validate the whole matrix, then run it."""
    if getattr(args, "out", None) is not None and not str(args.out).strip():  # was the default folder, unsaid
        raise ConfigError("--out needs a folder name, got an empty one")
    data = read_toml(args.matrix, "matrix")
    kind = data.get("kind")
    if kind is not None and kind not in MATRIX_KINDS:
        raise ConfigError(f"{args.matrix}: kind must be one of {', '.join(MATRIX_KINDS)} (or left out, for a matrix "
                          f"of cells), got {kind!r}")
    repeat = getattr(args, "repeat", None)
    if repeat is not None:
        if kind in ("gpu", "dynamic"):
            own = "repeat_frames and repeat_rays" if kind == "gpu" else "frames"
            raise ConfigError(f"{args.matrix}: --repeat is for matrices of cells and trimesh matrices; a {kind} "
                              f"matrix sets its own repetitions (its {own} keys)")
        if not 1 <= repeat <= MAX_REPEAT:
            raise ConfigError(f"--repeat: must be in 1..{MAX_REPEAT}, got {repeat}")
    if kind in ("gpu", "dynamic", "trimesh"):  # options only the runner of cells reads: refused, not ignored
        given = [option for option, name in (("--scheduler", "scheduler"), ("--workers", "workers"),
                                             ("--steady", "steady"), ("--retries", "retries"))
                 if getattr(args, name, None) is not None]
        if kind == "gpu" and getattr(args, "resume", False):
            given.append("--resume")
        if given:
            raise ConfigError(f"{args.matrix}: {', '.join(given)} {'is' if len(given) == 1 else 'are'} not for a "
                              f"{kind} matrix, which runs its own way (--scheduler, --workers, --steady and "
                              f"--retries act on matrices of benchmark cells only; --resume not on gpu matrices)")
    if kind in ("gpu", "dynamic"):  # their name is the default output folder's, as for cells
        check_matrix_name(args.matrix, data.get("name", Path(args.matrix).stem))
    device = getattr(args, "device", None) or data.get("device", "cpu")
    if data.get("kind") == "gpu" or device == "cuda":  # rays and frames on the CUDA device
        from engine.bench.gpu import run_gpu

        if data.get("kind") != "gpu":
            raise ConfigError(f"{args.matrix}: --device cuda runs matrices of kind = \"gpu\" (rays and frames on "
                              f"the GPU, e.g. benchmarks/gpu.toml); this matrix runs on the CPU")
        if device != "cuda":
            raise ConfigError(f"{args.matrix}: a kind = \"gpu\" matrix runs on device 'cuda', not {device!r}")
        out = Path(args.out) if args.out else Path("out") / f"bench-{data.get('name', Path(args.matrix).stem)}"
        run_gpu({**data, "device": "cuda"}, args.matrix, out)
        print(f"{data.get('name', Path(args.matrix).stem)}: wrote {out / 'gpu.json'}, {out / 'gpu.md'}")
        return 0
    if data.get("kind") == "dynamic":   # whole animation paths
        from engine.bench.dynamic import run_dynamic

        out = Path(args.out) if args.out else Path("out") / f"bench-{data.get('name', Path(args.matrix).stem)}"
        summary = run_dynamic(data, args.matrix, out, args.resume)
        print(f"{data.get('name', Path(args.matrix).stem)}: ran {summary['ran']} cell(s), skipped "
              f"{summary['skipped']}; wrote {', '.join(str(p) for p in summary['files'])}")
        return 0
    if data.get("kind") == "trimesh":  # mesh queries, not renders: their own small runner
        from engine.bench.trimesh_queries import cmd_trimesh_bench

        return cmd_trimesh_bench(args, data)
    matrix = load_matrix(args.matrix, repeat=args.repeat)
    out = Path(args.out) if args.out else Path("out") / f"bench-{matrix.name}"
    steady, retries = getattr(args, "steady", None), getattr(args, "retries", None)
    retries = 2 if retries is None else retries
    if steady is not None and not (steady >= 1.0 and math.isfinite(steady)):
        raise ConfigError(f"--steady must be a number >= 1 (how many times slower than its fastest the host may "
                          f"run around a cell), got {steady}")
    if isinstance(retries, bool) or not isinstance(retries, int) or not 0 <= retries <= 10:
        raise ConfigError(f"--retries must be an integer in 0..10, got {retries}")
    if getattr(args, "workers", None) is not None and getattr(args, "scheduler", None) is None:
        raise ConfigError("--workers sizes the local Dask cluster of --scheduler; give --scheduler too, or leave "
                          "--workers out (cells run here one at a time)")
    if steady is not None and getattr(args, "scheduler", None) is not None:
        raise ConfigError("--steady measures cells here, one after another; it does not combine with --scheduler")
    if getattr(args, "workers", None) is not None and getattr(args, "scheduler", None) not in (None, LOCAL):
        raise ConfigError(f"--workers sizes the local Dask cluster that --scheduler with no address starts; the "
                          f"scheduler at {args.scheduler} has its own workers (leave --workers out)")
    summary = run_matrix(matrix, out, resume=args.resume, scheduler=getattr(args, "scheduler", None),
                         workers=1 if getattr(args, "workers", None) is None else args.workers,
                         steady=steady, retries=retries)
    print(f"{matrix.name}: ran {summary['ran']} cell(s), skipped {summary['skipped']}; wrote "
          f"{', '.join(str(p) for p in summary['files'])}")
    return 0

"""The trimesh matrix (``kind = "trimesh"``): the same mesh queries through trimesh's default
ray backend (embreex, via ``trimesh.ray.ray_pyembree``) and through ``RayMeshIntersector``,
timed and checked against each other.

    kind = "trimesh"
    name = "trimesh"
    repeat = 5                      # timed repeats per query and backend (medians reported)
    rounds = 3                      # the repeats split into this many blocks per backend, the two
                                    # backends' blocks alternating (see ``_alternating_seconds``)
    threads = 0                     # numba threads for packetrt (0 = all); trimesh's embreex is one thread
    queries = ["first", "any", "all", "contains"]
    rays = 200000                   # rays per first / any query
    all_rays = 50000                # rays per all-hits query (trimesh re-casts from every hit)
    points = 50000                  # points per contains query
    render_path = true              # also time the render path's primary packets on the camera rays,
                                    # interleaved with the first-hit query on them
    one_thread = true               # also time packetrt on one numba thread, as a third side of the
                                    # rounds: the speed-up at the same thread count as embreex's

    [[mesh]]                        # catalog scenes, as in the other matrices
    scene = "bunny"
    lod = 0
    [[mesh]]
    scene = "bart-kitchen"

Ray sets per mesh: ``incoherent`` (origins around the mesh, aimed at random points inside its
box; seeded), ``primary`` (the scene's auto camera, one ray per pixel of a square image of
about ``rays`` pixels, row by row: coherent) and ``shuffled`` (the same camera rays in a seeded
random order: coherent rays in an order that hides it, which the intersector sorts, see
``engine.query.coherent.packing``). Points for ``contains``: uniform in the mesh's box.

Agreement per query and ray: ``first``: the same triangle, or hits at the same distance (within
1e-5 of the mesh's size: an edge shared by two triangles); ``any``: the same answer; ``all``: the
same number of hits; ``contains``: the same answer. For ``all``, ``trimesh_rehits`` counts the
disagreeing rays whose answers agree once trimesh's own rule is applied exactly: trimesh steps
1e-6 of ``mesh.scale`` past each hit, so a hit closer than that to the previous one is the same
crossing; where a ray grazes two coincident faces (the kitchen's back-to-back faces at one
distance), the stepped origin rounds back onto the second face's plane in float32 and Embree
reports it too (``stepping_rehits``). For ``contains``, ``trimesh_self_agree`` counts the points
on which a second call of trimesh's answers as its first: it re-casts the points its first line
leaves undecided in a random direction, so on an open mesh (the bunny's holes, the kitchen's
soup) its answers move from call to call and no backend can agree with all of them.

Speed-ups come two ways. ``speedup`` is trimesh's median time over packetrt's. ``speedup_paired``
(and ``speedup_1thread_paired``) pairs the k-th timed call of each backend, which lie in the same
round, a second or so apart: the median of the per-pair speed-ups with its 95% interval, the sign
test's (``engine.bench.paired_stats``), so that a speed-up near a target is read with the run's
noise beside it. The calls stay in blocks, each after its own warm-up: one call of each backend a
round, each backend warmed up once (session 33, 21 rounds), read packetrt 20-50% slower on the
kitchen's queries than blocks did in the run right after (incoherent first hits 1.24x against
2.04x, camera rays 1.27x against 2.61x; packetrt on one thread then beat it on two), as each
call found the caches and the worker threads cold after the other backend's.

Results go to ``OUT/results.jsonl`` (one
record per mesh, ray set and query, with the host's speed just before and after it: ``host``,
``engine.bench.host_speed``) and ``OUT/results.md`` (the table, with a host slow-down column).
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from engine.bench import host_speed
from engine.bench.matrix import check_labels, check_matrix_name
from engine.bench.paired_stats import paired_ratio
from engine.bench.results import free_backup_name, host_slowdown
from engine.core.atomic import output_folder, plain_json, write_text
from engine.core.errors import ConfigError

QUERIES = ("first", "any", "all", "contains")
#: The most numba threads a matrix may ask for, as a config's [render] threads.
MAX_THREADS = 1024
KEYS = ("kind", "name", "description", "repeat", "rounds", "threads", "queries", "rays", "all_rays", "points",
        "render_path", "one_thread", "mesh")


def parse(data: dict, source: str, repeat: int | None = None) -> dict:
    """The trimesh matrix as a plain dict; a wrong key or value is a ConfigError naming it."""
    unknown = set(data) - set(KEYS)
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {sorted(unknown)}; allowed: {', '.join(KEYS)}")
    spec = {"name": data.get("name", Path(source).stem), "description": data.get("description", ""),
            "repeat": repeat or data.get("repeat", 5), "rounds": data.get("rounds", 3),
            "threads": data.get("threads", 0),
            "queries": data.get("queries", list(QUERIES)), "rays": data.get("rays", 200000),
            "all_rays": data.get("all_rays", 50000), "points": data.get("points", 50000),
            "render_path": data.get("render_path", True), "one_thread": data.get("one_thread", True),
            "mesh": data.get("mesh", [])}
    for key in ("repeat", "rounds", "threads", "rays", "all_rays", "points"):
        value = spec[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < (0 if key == "threads" else 1):
            raise ConfigError(f"{source}: {key} must be a positive integer, got {value!r}")
    if spec["threads"] > MAX_THREADS:
        raise ConfigError(f"{source}: threads must be in 0..{MAX_THREADS} (0 = every core), got {spec['threads']}")
    for key in ("render_path", "one_thread"):
        if not isinstance(spec[key], bool):
            raise ConfigError(f"{source}: {key} must be true or false, got {spec[key]!r}")
    for key in ("name", "description"):
        if not isinstance(spec[key], str):
            raise ConfigError(f"{source}: {key} must be a string, got {spec[key]!r}")
    if not isinstance(spec["queries"], list) or not all(isinstance(q, str) for q in spec["queries"]):
        raise ConfigError(f"{source}: queries must be a list of names ({', '.join(QUERIES)}), "
                          f"got {spec['queries']!r}")
    bad = [q for q in spec["queries"] if q not in QUERIES]
    if bad or not spec["queries"]:
        raise ConfigError(f"{source}: queries {bad} unknown; allowed: {', '.join(QUERIES)}")
    if (not isinstance(spec["mesh"], list) or not spec["mesh"]
            or not all(isinstance(m, dict) and isinstance(m.get("scene"), str) for m in spec["mesh"])):
        raise ConfigError(f"{source}: give at least one [[mesh]] table with scene = \"<catalog name>\"")
    check_matrix_name(source, spec["name"])
    check_labels(source, "mesh", [entry.get("label", entry["scene"]) for entry in spec["mesh"]])
    return spec


def load_mesh(entry: dict):
    """(trimesh.Trimesh of the scene's triangles, Scene, label) for a [[mesh]] table."""
    import trimesh

    from scenes.catalog import load_named

    params = {k: v for k, v in entry.items() if k not in ("scene", "label")}
    scene = load_named(entry["scene"], params)
    tris = scene.triangles
    corners = np.stack([tris.v0, tris.v1, tris.v2], axis=1).astype(np.float64)
    mesh = trimesh.Trimesh(corners.reshape(-1, 3), np.arange(3 * len(corners)).reshape(-1, 3), process=False)
    return mesh, scene, entry.get("label", entry["scene"])


def incoherent_rays(mesh, n: int, seed: int = 0):
    """(origins, directions) f64[n,3]: from a box 3x the mesh's, aimed at points inside its box."""
    rng = np.random.default_rng(seed)
    lo, hi = mesh.bounds
    size = hi - lo
    origins = rng.uniform(lo - size, hi + size, size=(n, 3))
    targets = rng.uniform(lo, hi, size=(n, 3))
    return origins, targets - origins


#: Untimed warm-up before each side's timed calls: at least one call and this many seconds (at
#: most WARM_UP_CALLS calls). On this 2-core machine a query right after the other side's
#: one-thread calls ran up to 2x slower for about 0.1 s (both sides see the same rule).
WARM_UP_SECONDS = 0.3
WARM_UP_CALLS = 10


def _warm_up(call) -> None:
    start, calls = time.perf_counter(), 0
    while calls == 0 or (time.perf_counter() - start < WARM_UP_SECONDS and calls < WARM_UP_CALLS):
        call()  # JIT compilation, caches, threads and clocks up to speed
        calls += 1


def _timed_calls(call, repeat: int):
    """(seconds of each of ``repeat`` calls, the last answer), after the warm-up."""
    _warm_up(call)
    times = []
    answer = None
    for _ in range(repeat):
        start = time.perf_counter()
        answer = call()
        times.append(time.perf_counter() - start)
    return times, answer


def _alternating_seconds(sides, repeat: int, rounds: int):
    """[(median seconds, answer, seconds of every call in order)] of each side, ``sides`` being
    callables ``timed(k) -> (list of seconds, answer)`` that make k timed calls after their own
    warm-up. The ``repeat`` calls of
    each side are made in ``rounds`` blocks, the sides' blocks alternating and the side that goes
    first changing from round to round, so that a drift of this host over the seconds a query
    takes lands on every side alike. Timed as one stretch per side, trimesh's then packetrt's,
    the same matrix read the bunny's incoherent first hits at 1.57-2.00x in six runs (session 22)."""
    rounds = max(1, min(rounds, repeat))
    times = [[] for _ in sides]
    answers = [None] * len(sides)
    for r in range(rounds):
        calls = repeat // rounds + (1 if r < repeat % rounds else 0)
        order = range(len(sides)) if r % 2 == 0 else reversed(range(len(sides)))
        for k in order:
            seconds, answers[k] = sides[k](calls)
            times[k] += seconds
    return [(float(np.median(t)), a, t) for t, a in zip(times, answers)]


def _plane_t(mesh, origins, directions, ray, tri):
    unit = directions[ray] / np.linalg.norm(directions[ray], axis=1, keepdims=True)
    normal = mesh.face_normals[tri]
    with np.errstate(divide="ignore", invalid="ignore"):
        return (np.einsum("ij,ij->i", mesh.triangles[tri, 0] - origins[ray], normal)
                / np.einsum("ij,ij->i", unit, normal))


def agreement(query: str, mesh, ours, theirs, origins=None, directions=None) -> int:
    """How many rays (points) the two answers agree on, by the rules in the module doc."""
    if query == "first":
        same = ours == theirs
        differ = np.flatnonzero(~same & (ours >= 0) & (theirs >= 0))
        if len(differ):
            a = _plane_t(mesh, origins, directions, differ, ours[differ])
            b = _plane_t(mesh, origins, directions, differ, theirs[differ])
            same[differ] = np.abs(a - b) <= 1e-5 * mesh.scale
        return int(same.sum())
    if query == "all":
        n = len(origins)
        return int((np.bincount(ours[1], minlength=n) == np.bincount(theirs[1], minlength=n)).sum())
    return int((np.asarray(ours) == np.asarray(theirs)).sum())


def stepping_rehits(mesh, ours, theirs, origins, directions) -> int:
    """How many rays with different all-hit counts (ours, theirs: (index_tri, index_ray)) have the
    same count once trimesh's hits closer than its step (1e-6 of ``mesh.scale``, float64 plane
    distances) to the previous one are dropped: hits trimesh's stepping re-found, not crossings
    packetrt missed."""
    n = len(origins)
    count_ours = np.bincount(ours[1], minlength=n)
    count_theirs = np.bincount(theirs[1], minlength=n)
    step = 1e-6 * mesh.scale
    explained = 0
    for ray in np.flatnonzero(count_theirs > count_ours):
        tris = theirs[0][theirs[1] == ray]
        t = np.sort(_plane_t(mesh, origins, directions, np.full(len(tris), ray), tris))
        crossings = 1 + int((np.diff(t) >= step).sum()) if len(t) else 0
        explained += crossings == count_ours[ray]
    return explained


def _same_answers(a, b) -> bool:
    """Whether two answers of one query (an array, or a tuple of arrays) are equal."""
    if isinstance(a, tuple):
        return isinstance(b, tuple) and len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
    return np.array_equal(a, b)


def _paired_times(first, second, repeat: int):
    """(seconds of each call of first, answer of first, seconds of each call of second):
    ``repeat`` calls of each, alternating which goes first, after each one's warm-up. For two
    packetrt calls whose ratio is quoted: timed one after the other, this host's drift between
    the two stretches of calls (10-30%) moved the ratio more than any change measured (bunny
    camera rays, API against the render path: 1.63-2.06x in three matrix runs, 1.49-1.53x
    interleaved)."""
    _warm_up(first)
    _warm_up(second)
    times_first, times_second = [], []
    answer = None
    for k in range(repeat):
        for call, times in ((first, times_first), (second, times_second))[::1 if k % 2 == 0 else -1]:
            start = time.perf_counter()
            result = call()
            times.append(time.perf_counter() - start)
            if call is first:
                answer = result
    return times_first, answer, times_second


def render_path_trace(scene, width: int):
    """(call, rays): a call that traces the render path's primary query once (camera rays in
    8 x 8 packets, Ranged + pinhole frusta, as the paper's renders trace them) on a width x width
    image of the scene, and its number of rays."""
    from engine.core.bvh import build_bvh, scene_bounds
    from engine.packet.layout import make_batch
    from engine.render.camera import camera_rays
    from engine.render.plugins import make_frustum, make_traversal
    from engine.render.tracer import Tracer

    bvh = build_bvh(scene.triangles)
    tracer = Tracer(bvh, scene.triangles, scene_bounds(bvh), {"primary": make_traversal("ranged")},
                    {"primary": make_frustum("pinhole")})
    tracer.prepare()
    org, d = camera_rays(scene, width, width)
    count = width * width
    rays, packets = make_batch("primary", org, d, np.zeros(count), np.full(count, np.inf),
                               np.arange(count, dtype=np.int32), np.ones((count, 3)), width, width, 8)
    return (lambda: tracer.trace("primary", "intersect", rays, packets)), count


def _time_query(theirs, ours, ours_1, call, args, render_call, repeat: int, rounds: int):
    """((median seconds, answer, seconds of every call) of trimesh's backend, of packetrt, of
    packetrt on one thread or (None, None, None) without ``ours_1``; the render path's seconds
    per call, [] without ``render_call``): method ``call`` of each intersector on ``args``,
    ``repeat`` calls made in ``rounds`` alternating blocks (``_alternating_seconds``), each block
    after its own warm-up. ``render_call``, the render path's primary trace on the same camera,
    is timed interleaved with packetrt's calls."""
    render_times = []

    def ask(intersector):
        return lambda: getattr(intersector, call)(*args)

    def timed(intersector):
        return lambda k: _timed_calls(ask(intersector), k)

    def ours_with_render(k):
        times, answer, render = _paired_times(ask(ours), render_call, k)
        render_times.extend(render)
        return times, answer

    sides = [timed(theirs), ours_with_render if render_call is not None else timed(ours)]
    if ours_1 is not None:  # packetrt at the thread count of trimesh's embreex backend
        sides.append(timed(ours_1))
    measured = _alternating_seconds(sides, repeat, rounds)
    one = measured[2] if ours_1 is not None else (None, None, None)
    return measured[0], measured[1], one, render_times


def run(spec: dict, out: Path, progress=print) -> list:
    """Every (mesh, ray set, query) record; written to out/results.jsonl and out/results.md."""
    import numba
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector as TrimeshDefault

    from engine.core.threads import numba_threads
    from engine.query.intersector import RayMeshIntersector
    from engine.render.camera import camera_rays

    # numba runs at most its own pool's threads: the records say what ran.
    threads = min(spec["threads"] or numba.config.NUMBA_NUM_THREADS, numba.config.NUMBA_NUM_THREADS)
    output_folder(out, "--out")
    records = []
    with numba_threads(threads):  # the render path's trace too; the caller's count comes back
        for entry in spec["mesh"]:
            mesh, scene, label = load_mesh(entry)
            ours, theirs = RayMeshIntersector(mesh, threads=threads), TrimeshDefault(mesh)
            ours_1 = RayMeshIntersector(mesh, threads=1) if spec["one_thread"] else None
            side = int(np.sqrt(spec["rays"]))
            cam_o, cam_d = camera_rays(scene, side, side)
            camera = (cam_o.astype(np.float64), cam_d.astype(np.float64))
            shuffle = np.random.default_rng(2).permutation(len(cam_o))
            ray_sets = {"incoherent": incoherent_rays(mesh, spec["rays"]), "primary": camera,
                        "shuffled": (camera[0][shuffle], camera[1][shuffle])}
            render_call, render_rays = render_path_trace(scene, side) if spec["render_path"] else (None, 0)
            rng = np.random.default_rng(1)
            points = rng.uniform(*mesh.bounds, size=(spec["points"], 3))
            for set_name, (origins, directions) in ray_sets.items():
                for query in spec["queries"]:
                    if query == "contains" and set_name != "incoherent":
                        continue  # contains takes points, not rays: once per mesh
                    if query == "first":
                        args, call = (origins, directions), "intersects_first"
                    elif query == "any":
                        args, call = (origins, directions), "intersects_any"
                    elif query == "all":
                        n = spec["all_rays"]
                        args, call = (origins[:n], directions[:n]), "intersects_id"
                    else:
                        args, call = (points,), "contains_points"
                    render = render_call if set_name == "primary" and query == "first" else None
                    before = host_speed.measure()
                    (t_theirs, a_theirs, s_theirs), (t_ours, a_ours, s_ours), (t_one, a_one, s_one), render_times = \
                        _time_query(theirs, ours, ours_1, call, args, render, spec["repeat"], spec["rounds"])
                    host = {"before": before, "after": host_speed.measure()}
                    render_rate = render_rays / float(np.median(render_times)) / 1e6 if render_times else None
                    n = len(args[0])
                    agree = agreement(query, mesh, a_ours, a_theirs, *args) if query != "contains" else \
                        agreement(query, mesh, a_ours, a_theirs)
                    rehits = stepping_rehits(mesh, a_ours, a_theirs, *args) if query == "all" else None
                    # trimesh re-casts undecided points in a random direction: its own two calls
                    # can differ, the measure of what agreement means on an open mesh.
                    itself = int((theirs.contains_points(points) == a_theirs).sum()) if query == "contains" else None
                    record = {"mesh": label, "triangles": len(mesh.faces), "rays": set_name if query != "contains" else
                              "points", "query": query, "n": n, "repeat": spec["repeat"], "rounds": spec["rounds"],
                              "threads": threads,
                              "trimesh_seconds": t_theirs, "packetrt_seconds": t_ours,
                              "trimesh_mrays": n / t_theirs / 1e6, "packetrt_mrays": n / t_ours / 1e6,
                              "speedup": t_theirs / t_ours, "speedup_paired": paired_ratio(s_theirs, s_ours),
                              "agree": agree, "trimesh_rehits": rehits, "trimesh_self_agree": itself,
                              "packetrt_1thread_seconds": t_one,
                              "same_on_1thread": _same_answers(a_ours, a_one) if t_one else None,
                              "speedup_1thread": t_theirs / t_one if t_one else None,
                              "speedup_1thread_paired": paired_ratio(s_theirs, s_one) if t_one else None,
                              "render_path_mrays": render_rate, "host": host}
                    records.append(record)
                    one = f" (1 thread x{record['speedup_1thread']:.2f})" if t_one else ""
                    progress(f"{label:>14} {record['rays']:>10} {query:>8}: trimesh {record['trimesh_mrays']:6.2f}  "
                             f"packetrt {record['packetrt_mrays']:6.2f} Mrays/s  x{record['speedup']:.2f} "
                             f"(paired {_interval(record['speedup_paired'])}){one}  "
                             f"agree {agree}/{n}" + (f" (+{rehits} trimesh re-hits)" if rehits else "")
                             + (f" (trimesh with itself {itself}/{n})" if itself is not None else ""))
    write_text(out / "results.jsonl", "".join(json_line(record) for record in records))
    write_text(out / "results.md", markdown_table(records, trimesh.__version__))
    return records


def markdown_table(records: list, trimesh_version: str) -> str:
    first = records[0] if records else {}
    lines = [f"trimesh {trimesh_version} default backend (embreex, 1 thread) vs packetrt RayMeshIntersector "
             f"({first.get('threads', '?')} numba threads); medians of {first.get('repeat', '?')} in "
             f"{first.get('rounds', 1)} alternating rounds per backend",
             "", "Speed-up: trimesh's median time over packetrt's. Paired: the k-th calls of the two backends "
             "(the same round, a second or so apart) paired, the median speed-up and its 95% interval (the sign "
             "test's): a target speed-up is met where the interval lies above it.",
             "", "Agree: rays (points) with the same answer; \"+k re-hits\": k more rays agree once trimesh's own "
             "step (1e-6 of mesh.scale past each hit) is applied exactly to its hits; \"trimesh with itself k\": "
             "points on which two contains calls of trimesh agree (it re-casts undecided points in a random "
             "direction), the ceiling for agreement on an open mesh (engine.bench.trimesh_queries).",
             "", "Host slow-down: how many times slower than the run's fastest moment the host ran around the "
             "query (engine.bench.host_speed); compare rows near 1.00.",
             "", "| mesh | rays | query | n | trimesh Mrays/s | packetrt Mrays/s | speed-up | speed-up, paired [95%] | "
             "speed-up, 1 thread each | 1 thread, paired [95%] | agree | render path Mrays/s | host slow-down |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r, slow in zip(records, host_slowdown(records)):
        render = f"{r['render_path_mrays']:.2f}" if r["render_path_mrays"] else ""
        one = f"{r['speedup_1thread']:.2f}" if r.get("speedup_1thread") else ""
        lines.append(f"| {r['mesh']} | {r['rays']} | {r['query']} | {r['n']:,} | {r['trimesh_mrays']:.2f} | "
                     f"{r['packetrt_mrays']:.2f} | {r['speedup']:.2f} | {_interval(r.get('speedup_paired'))} | "
                     f"{one} | {_interval(r.get('speedup_1thread_paired'))} | {r['agree']:,}/{r['n']:,}{_rehits(r)} | "
                     f"{render} | {'' if slow is None else f'{slow:.2f}'} |")
    return "\n".join(lines) + "\n"


def _rehits(record) -> str:
    """" (+k re-hits)" for an all-hits record with k rays explained by trimesh's stepping, " (trimesh
    with itself k)" for a contains record, else ""."""
    if record.get("trimesh_self_agree") is not None:
        return f" (trimesh with itself {record['trimesh_self_agree']:,})"
    return f" (+{record['trimesh_rehits']:,} re-hits)" if record.get("trimesh_rehits") else ""


def _interval(paired) -> str:
    """"m [lo, hi]" of a (median, low, high) paired speed-up; "" for None."""
    return "" if not paired else f"{paired[0]:.2f} [{paired[1]:.2f}, {paired[2]:.2f}]"


def cmd_trimesh_bench(args, data: dict) -> int:
    """``packetrt bench benchmarks/trimesh.toml``: run a trimesh matrix."""
    spec = parse(data, args.matrix, args.repeat)
    if getattr(args, "resume", False):
        raise ConfigError(f"{args.matrix}: a trimesh matrix is measured whole, in alternating rounds; --resume does "
                          f"not apply (run it again without)")
    out = Path(args.out) if args.out else Path("out") / f"bench-{spec['name']}"
    earlier = out / "results.jsonl"
    if earlier.is_file() and earlier.stat().st_size:  # another run's results, as the cell runner keeps them
        backup = free_backup_name(earlier)
        os.replace(earlier, backup)
        print(f"packetrt bench: earlier results moved to {backup}", file=sys.stderr)
    records = run(spec, out, progress=lambda line: print(line, file=sys.stderr))
    print(f"{spec['name']}: {len(records)} queries; wrote {out / 'results.jsonl'}, {out / 'results.md'}")
    return 0


def json_line(record: dict) -> str:
    """One strict-JSON line (NaN and infinities as null) of a record."""
    return json.dumps(plain_json(record)) + "\n"

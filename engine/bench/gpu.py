"""The GPU benchmark (``kind = "gpu"`` matrices): rays and whole frames on the CUDA device.

For each scene of the matrix, on the lent GPU, in one process:

1. **Ray sets** (``gpu_rays``): the scene's camera rays and rays spawned at their hits (shadow
   rays to the first light and to every light, mirror reflections, cosine-distributed bounces),
   each traced by every device traversal of the matrix -- median of ``repeat_rays`` warm calls,
   kernels compiled apart -- and, when Mitsuba 3 is importable, by its ``cuda_ad_rgb`` variant
   on the very same rays (``engine.bench.mitsuba_yardstick``). Every answer is checked against
   Embree with the audit's tie-aware rules.
2. **Frames**: the scene's recursion preset rendered by ``GpuWhittedRenderer`` with each
   traversal: compile time apart, median of ``repeat_frames`` frames, FPS.
3. **The image check**: the GPU frame against the CPU renderer's, pixel by pixel; every pixel
   off by more than 1/255 is listed with its reason: a tie (an audit of the GPU frame found a
   ray of that pixel whose answer ties Embree's at a shared edge) or unexplained.
4. **The audit**: every ray of a GPU frame against Embree, per traversal.

Results go to ``OUT/gpu.json`` (everything) and ``OUT/gpu.md`` (the README's tables), both
through the atomic writer.
"""
from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np

from engine.bench.dynamic import cell_config
from engine.bench.matrix import check_labels
from engine.bench.gpu_pixels import PixelRecorder, explain
from engine.bench.gpu_rays import RAY_SETS, ray_sets
from engine.core import atomic
from engine.core.errors import ConfigError
from engine.core.types import RAY_KINDS, Packets
from engine.render.device_names import device_traversal_name

TOP_KEYS = {"kind", "name", "description", "device", "resolution", "repeat_rays", "repeat_frames", "scene",
            "variant", "audit", "image_check"}
SCENE_KEYS = {"name", "params", "recursion", "rays", "resolution", "ray_resolutions"}
# rays = false: frames only, no ray-set timings; repeat_frames: this variant's frames per scene;
# options: per-plugin option tables, as a config's [options.NAME]; traversal: one device traversal
# for every ray kind, or a table naming one per kind (every kind; frames only, rays = false).
VARIANT_KEYS = {"label", "traversal", "rays", "repeat_frames", "options"}


def _fail(source: str, where: str, message: str):
    raise ConfigError(f"{source}: {where}: {message}")


def check_matrix(data: dict, source: str) -> None:
    """Keys and names of a gpu matrix; mistakes name the file and key."""
    unknown = set(data) - TOP_KEYS
    if unknown:
        _fail(source, "top level", f"unknown key(s) {sorted(unknown)}; allowed: {', '.join(sorted(TOP_KEYS))}")
    if data.get("device", "cuda") != "cuda":
        _fail(source, "device", f"a gpu matrix runs on device 'cuda', got {data.get('device')!r}")
    for key in ("scene", "variant"):
        tables = data.get(key)
        if not isinstance(tables, list) or not tables or not all(isinstance(t, dict) for t in tables):
            _fail(source, "top level", f"needs one or more [[{key}]] tables, got {key} = {tables!r}")
    for i, scene in enumerate(data["scene"]):
        if set(scene) - SCENE_KEYS:
            _fail(source, f"scene {i + 1}", f"unknown key(s) {sorted(set(scene) - SCENE_KEYS)}; allowed: "
                  f"{', '.join(sorted(SCENE_KEYS))}")
        rays = scene.get("rays", [])
        if not isinstance(rays, list):
            _fail(source, f"scene {i + 1} rays", f"must be a list of ray sets ({', '.join(RAY_SETS)}), got {rays!r}")
        for name in rays:
            if name not in RAY_SETS:
                _fail(source, f"scene {i + 1} rays", f"unknown ray set {name!r}; allowed: {', '.join(RAY_SETS)}")
        if "path" in scene or not isinstance(scene.get("name"), str):  # the ray sets load catalog scenes
            _fail(source, f"scene {i + 1}", f"needs name = \"<catalog scene>\" (a gpu matrix takes catalog scenes, "
                                            f"not paths), got {dict(scene)!r}")
    for i, variant in enumerate(data["variant"]):
        if set(variant) - VARIANT_KEYS or "traversal" not in variant or "label" not in variant:
            _fail(source, f"variant {i + 1}", f"needs label and traversal (bvh, wide or rayspace), got {sorted(variant)}")
        traversal = variant["traversal"]
        if isinstance(traversal, dict):
            if set(traversal) != set(RAY_KINDS) or not all(isinstance(v, str) for v in traversal.values()):
                _fail(source, f"variant {i + 1} traversal", f"a table needs a traversal name for each of "
                      f"{', '.join(RAY_KINDS)}, got {traversal!r}")
            if variant.get("rays", True):
                _fail(source, f"variant {i + 1}", "a traversal per ray kind times frames only: set rays = false")
        elif not isinstance(traversal, str):
            _fail(source, f"variant {i + 1} traversal", f"must be a name or a table per ray kind, got {traversal!r}")
        for kind, name in variant_traversals(variant).items():
            try:
                device_traversal_name(name, kind)
            except ConfigError as exc:
                _fail(source, f"variant {i + 1}", str(exc))
    check_labels(source, "variant", [variant["label"] for variant in data["variant"]])
    # Every (scene, variant) frame's config, before any GPU work: scene, preset and options
    # names fail here, not when that scene's frames start.
    for scene in data["scene"]:
        for variant in data["variant"]:
            cell_config({"resolution": scene.get("resolution", data.get("resolution", 1024))}, scene,
                        {"label": variant["label"], "options": variant.get("options", {})}, source)


def variant_traversals(variant: dict) -> dict:
    """{ray kind: device traversal name} of a gpu matrix variant."""
    traversal = variant["traversal"]
    return dict(traversal) if isinstance(traversal, dict) else dict.fromkeys(RAY_KINDS, traversal)


def _median_call_seconds(launch, repeat: int, cuda) -> float:
    """Median wall time of ``repeat`` calls of ``launch()`` each followed by a wait for the GPU,
    after one warm call: what a Python caller pays per call, measured as Mitsuba's calls are."""
    launch()
    cuda.synchronize()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        launch()
        cuda.synchronize()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _kernel_seconds(launch, repeat: int, cuda) -> float:
    """GPU time per call of ``launch()``: ``repeat`` calls back to back between two CUDA events,
    so the host's launch cost overlaps the GPU's work (the kernels alone)."""
    launch()
    begin, end = cuda.event(), cuda.event()
    begin.record()
    for _ in range(repeat):
        launch()
    end.record()
    end.synchronize()
    return begin.elapsed_time(end) / 1e3 / repeat


def time_ray_set(traversal, query: str, rays, repeat: int, cuda) -> tuple[dict, object]:
    """({"seconds": median call, "kernel_seconds"}, host answer) of a device traversal on one
    host RaySet: Hits for "closest", bool[R] for "occluded". Rays and their count go to the
    device once, outside the timing."""
    from engine.core.types import Hits
    from engine.gpu.scene_upload import upload

    n = rays.org.shape[0]
    org, dirs, tmin, tmax, pixel = (upload(a) for a in (rays.org, rays.dir, rays.tmin, rays.tmax, rays.pixel))
    count = upload(np.array([n], np.int32))
    width, height = rays.screen
    # The launch prepared once, as the frame prepares its launches (``engine.gpu.launch``).
    if query == "closest":
        out = (cuda.device_array(n, np.float32), cuda.device_array(n, np.int32), cuda.device_array(n, np.float32),
               cuda.device_array(n, np.float32))
        launch = traversal.queue_launch("closest", org, dirs, tmin, tmax, pixel, count, n, width, height, *out)
    else:
        flags = cuda.device_array(n, np.uint8)
        launch = traversal.queue_launch("occluded", org, dirs, tmin, tmax, pixel, count, n, width, height, flags)
    timing = {"seconds": _median_call_seconds(launch, repeat, cuda), "kernel_seconds": _kernel_seconds(launch, repeat, cuda)}
    if query == "closest":
        return timing, Hits(*(a.copy_to_host() for a in out))
    return timing, flags.copy_to_host().astype(bool)


def _checked(rays, query, answer, oracle, tris, closest_ours=None) -> dict:
    """{"checked", "ties", "mismatches"} of an answer against Embree's (tie-aware); an occlusion
    answer also needs our closest hits of the same rays (``closest_ours``) to classify ties."""
    from validation.compare import compare_hits, compare_occlusion

    theirs = oracle.intersect(rays.batch)  # once: the comparison and the examples both read it
    if query == "closest":
        result = compare_hits(rays.batch, answer, theirs, tris)
    else:
        result = compare_occlusion(rays.batch, answer, oracle.occluded(rays.batch), tris, closest_ours, theirs)
    examples = []
    for i in np.flatnonzero(result.mismatch)[:5]:
        ours = answer if query == "closest" else closest_ours
        examples.append({"org": rays.org[i].tolist(), "dir": rays.dir[i].tolist(), "tmax": float(rays.tmax[i]),
                         "ours": {"prim": int(ours.prim[i]), "t": float(ours.t[i])},
                         "embree": {"prim": int(theirs.prim[i]), "t": float(theirs.t[i])}})
    return {"checked": int(rays.org.shape[0]), "ties": int(result.tie.sum()), "mismatches": int(result.mismatch.sum()),
            "examples": examples}


def _cpu_agreement(scene, bvh, rays, answer) -> dict:
    """How many rays' (prim, t, u, v) differ bit for bit from the CPU ``single`` traversal's."""
    from engine.render.plugins import make_traversal
    from engine.render.tracer import Tracer

    tracer = Tracer(bvh, scene.triangles, None, {"reflection": make_traversal("single")}, {"reflection": None})
    packets = Packets(np.array([0, rays.org.shape[0]], np.int32), 2, 1, 1)
    cpu = tracer.trace("reflection", "intersect", rays.batch._replace(kind="reflection"), packets)
    differ = (cpu.prim != answer.prim) | (cpu.t != answer.t) | (cpu.u != answer.u) | (cpu.v != answer.v)
    return {"checked": int(rays.org.shape[0]), "differ": int(differ.sum()),
            "different_triangle": int((cpu.prim != answer.prim).sum())}


def _mitsuba(scene):
    """(yardstick module, MitsubaScene or None, why not) for Mitsuba 3's cuda_ad_rgb variant."""
    try:
        from engine.bench import mitsuba_yardstick as yardstick
    except ImportError as error:
        return None, None, f"no yardstick module ({error})"
    problem = yardstick.mitsuba_available("cuda_ad_rgb")
    if problem:
        return yardstick, None, problem
    t = scene.triangles
    return yardstick, yardstick.MitsubaScene(t.v0, t.v1, t.v2, "cuda_ad_rgb"), None


def _scene_rays(scene_table, scene, bvh, variants, matrix, cuda, tris_device, bvh_device) -> list:
    """Rows of the ray-set table of one scene."""
    from engine.gpu.traversals import make_device_traversal, walks_far_first
    from engine.render.config import RenderConfig
    from validation.audit import make_oracle

    rows = []
    oracle = make_oracle("embree", scene.triangles)
    sides = scene_table.get("ray_resolutions", [matrix.get("resolution", 1024)])
    wanted = scene_table.get("rays", ["primary"])
    yardstick, mitsuba, mitsuba_problem = _mitsuba(scene)
    for side in sides:
        for name, (query, rays) in ray_sets(scene, bvh, side, side, [w for w in wanted if
                                                                      side == sides[0] or w == "primary"]).items():
            row = {"scene": scene.name, "rays": name, "resolution": side, "count": int(rays.org.shape[0]),
                   "query": query}
            for variant in variants:
                if not variant.get("rays", True):
                    continue
                # Shadow ray sets are walked as a frame walks them by default ([render] shadow_order).
                traversal = make_device_traversal(variant["traversal"], bvh_device, tris_device, scene.triangles,
                                                  far_first=walks_far_first(RenderConfig().shadow_order))
                timing, answer = time_ray_set(traversal, query, rays, matrix.get("repeat_rays", 10), cuda)
                closest = time_ray_set(traversal, "closest", rays, 1, cuda)[1] if query == "occluded" else None
                row[variant["label"]] = {**timing, "grays_per_s": rays.org.shape[0] / timing["seconds"] / 1e9,
                                         "kernel_grays_per_s": rays.org.shape[0] / timing["kernel_seconds"] / 1e9,
                                         "embree": _checked(rays, query, answer, oracle, scene.triangles,
                                                            closest)}
            if query == "closest" and name == "primary" and side == sides[0]:
                row["cpu_single"] = _cpu_agreement(scene, bvh, rays, answer)
            if mitsuba is not None:
                timing = yardstick.time_queries(mitsuba, rays.org, rays.dir, rays.tmin, rays.tmax,
                                                "closest" if query == "closest" else "occluded",
                                                repeats=matrix.get("repeat_rays", 10))
                row["mitsuba"] = {"seconds": timing["median_seconds"], "grays_per_s": timing["grays_per_s"]}
            else:
                row["mitsuba"] = {"skipped": mitsuba_problem}
            rows.append(row)
            print(f"  rays {name} {side}: " + ", ".join(
                f"{k} {v['grays_per_s']:.2f} Grays/s" for k, v in row.items() if isinstance(v, dict) and
                "grays_per_s" in v), flush=True)
    return rows


def _frames(scene_table, variants, matrix, source) -> tuple[list, list, list]:
    """(frame rows, image-check rows, audit rows) of one scene's recursion preset."""
    from dataclasses import replace

    from engine.gpu.frame import GpuWhittedRenderer
    from engine.render.whitted import WhittedRenderer
    from scenes.catalog import scene_from_config
    from validation.audit import AuditObserver, make_oracle

    frames, images, audits = [], [], []
    cpu_image = None
    for variant in variants:
        repeat = variant.get("repeat_frames", matrix.get("repeat_frames", 20))
        config = cell_config({"resolution": scene_table.get("resolution", matrix.get("resolution", 1024))},
                             scene_table, {"label": variant["label"], "options": variant.get("options", {})}, source)
        config = replace(config, render=replace(config.render, device="cuda"),
                         traversal=replace(config.traversal, **variant_traversals(variant)))
        scene = scene_from_config(config.scene, config.override)
        renderer = GpuWhittedRenderer(scene, config)
        compile_seconds = renderer.warm_up()
        results = [renderer.render() for _ in range(repeat)]
        totals = [r.seconds["total"] for r in results]
        median = statistics.median(totals)
        last = results[-1]
        # One more frame with every launch timed alone (host cost, and launch to finish).
        renderer.profile = {}
        enqueue_start = time.perf_counter()
        renderer.render()
        profiled_total = time.perf_counter() - enqueue_start
        profile = {name: {"host_ms": row[0] * 1e3, "to_finish_ms": row[1] * 1e3, "launches": row[2]}
                   for name, row in renderer.profile.items()}
        renderer.profile = None
        print("  profile (host ms / launch-to-finish ms / launches): " + "; ".join(
            f"{k} {v['host_ms']:.2f}/{v['to_finish_ms']:.2f}/{v['launches']}" for k, v in profile.items()), flush=True)
        rayspace = last.extra.get("rayspace", {}).get("primary")
        frames.append({"rayspace_totals": rayspace, "profile": profile, "profiled_frame_seconds": profiled_total,
                       "scene": scene.name, "recursion": scene_table.get("recursion"), "variant": variant["label"],
                       "resolution": [config.render.width, config.render.height], "frames": repeat,
                       "median_seconds": median, "fps": 1 / median, "compile_seconds": compile_seconds,
                       "trace_seconds": last.seconds["trace"], "rays": last.rays,
                       "upload_seconds": renderer.prepare_seconds})
        print(f"  frame {scene.name} {variant['label']}: {median * 1e3:.2f} ms = {1 / median:.1f} FPS "
              f"(median of {repeat}; compile {compile_seconds:.1f} s apart)", flush=True)
        if matrix.get("audit", True) or matrix.get("image_check", True):
            oracle = make_oracle("embree", scene.triangles)
            observer = AuditObserver(scene, renderer.bvh, [oracle])
            gpu_rays = PixelRecorder(observer)
            renderer.observer = gpu_rays
            audited = renderer.render()
            renderer.observer = None
            report = observer.report()
            audits.append({"scene": scene.name, "variant": variant["label"], "checked": report["rays_checked"],
                           "by_kind": report["by_kind"], "mismatches": report["mismatch_count"],
                           "examples": report["mismatches"][:5]})
            print(f"  audit {scene.name} {variant['label']}: {report['rays_checked']:,} rays, "
                  f"{report['mismatch_count']} mismatches", flush=True)
            if matrix.get("image_check", True):
                if cpu_image is None:
                    cpu_rays = PixelRecorder()
                    cpu_config = replace(config, render=replace(config.render, device="cpu"),
                                         traversal=replace(config.traversal, **{k: "single" for k in (
                                             "primary", "shadow", "reflection", "refraction")}),
                                         frustum=replace(config.frustum, **{k: "none" for k in (
                                             "primary", "shadow", "reflection", "refraction")}))
                    cpu_image = WhittedRenderer(scene, cpu_config, observer=cpu_rays).render().image
                images.append(image_check(scene.name, variant["label"], cpu_image, audited.image,
                                          observer.tie_pixels, config.render.width, cpu_rays, gpu_rays))
    return frames, images, audits


def image_check(scene: str, variant: str, cpu: np.ndarray, gpu: np.ndarray, tie_pixels: set, width: int,
                cpu_rays=None, gpu_rays=None) -> dict:
    """The pixels where the GPU image differs from the CPU one by more than 1/255, each with its
    reason: the first ray of the pixel whose rays or answers differ between the two renders
    (``engine.bench.gpu_pixels``), and whether a ray of the pixel ties Embree's answer."""
    difference = np.abs(cpu - gpu).max(axis=2)
    ys, xs = np.nonzero(difference > 1 / 255)
    reasons = explain(list(zip(xs.tolist(), ys.tolist())), width, cpu_rays, gpu_rays) \
        if cpu_rays is not None and len(xs) <= 5000 else {}
    listed = [{"x": int(x), "y": int(y), "difference": float(difference[y, x]),
               "reason": reasons.get(int(y) * width + int(x), "not examined"),
               "tie_with_embree": int(y) * width + int(x) in tie_pixels} for y, x in zip(ys, xs)]
    unexplained = sum(1 for p in listed if not p["tie_with_embree"])
    summary = {}
    for p in listed:
        summary[p["reason"].split(":")[0].split(" (")[0]] = summary.get(p["reason"].split(":")[0].split(" (")[0], 0) + 1
    return {"scene": scene, "variant": variant, "pixels": int(difference.size), "over_1_255": len(listed),
            "reasons": summary,
            "share": len(listed) / difference.size, "unexplained": unexplained,
            "max_difference": float(difference.max()), "listed": listed[:200]}


def table(result: dict) -> str:
    """The README's GPU tables (markdown) of a gpu.json result."""
    labels = [label for label in result["labels"] if any(label in row for row in result["rays"])]
    lines = [f"GPU: {result['device']}; {result['date']}"]
    if result["rays"]:  # a matrix of frames only has no ray-set table
        lines += ["", "| scene | rays | count | " + " | ".join(labels) + " | Mitsuba 3 cuda_ad_rgb | ours / Mitsuba |",
                  "|---|---|---:|" + "---:|" * (len(labels) + 2)]
    for row in result["rays"]:
        cells = []
        for label in labels:
            v = row.get(label, {})
            cells.append(f"{v['grays_per_s']:.2f} Grays/s ({v['seconds'] * 1e3:.2f} ms a call; kernel "
                         f"{v['kernel_grays_per_s']:.2f}; {v['embree']['mismatches']} mismatches, "
                         f"{v['embree']['ties']} ties)" if "grays_per_s" in v else "-")
        mitsuba = row.get("mitsuba", {})
        best = max((row[l]["grays_per_s"] for l in labels if "grays_per_s" in row.get(l, {})), default=0)
        ratio = f"{best / mitsuba['grays_per_s']:.2f}x" if "grays_per_s" in mitsuba else "-"
        m = f"{mitsuba['grays_per_s']:.2f} Grays/s ({mitsuba['seconds'] * 1e3:.2f} ms)" if "grays_per_s" in mitsuba \
            else f"skipped: {mitsuba.get('skipped', '?')}"
        lines.append(f"| {row['scene']} | {row['rays']} {row['resolution']}² | {row['count']:,} | "
                     + " | ".join(cells) + f" | {m} | {ratio} |")
    lines += ["", "| scene | recursion | traversal | size | frame (median) | FPS | compile (apart) |",
              "|---|---|---|---|---:|---:|---:|"]
    for f in result["frames"]:
        lines.append(f"| {f['scene']} | {f['recursion']} | {f['variant']} | {f['resolution'][0]}x{f['resolution'][1]} "
                     f"| {f['median_seconds'] * 1e3:.2f} ms | {f['fps']:.1f} | {f['compile_seconds']:.1f} s |")
    lines += ["", "| scene | traversal | rays audited | mismatches | pixels > 1/255 vs CPU | unexplained |",
              "|---|---|---:|---:|---:|---:|"]
    images = {(i["scene"], i["variant"]): i for i in result["images"]}
    for a in result["audits"]:
        i = images.get((a["scene"], a["variant"]), {})
        lines.append(f"| {a['scene']} | {a['variant']} | {a['checked']:,} | {a['mismatches']} | "
                     f"{i.get('over_1_255', '-')} ({100 * i.get('share', 0):.4f}%) | {i.get('unexplained', '-')} |")
    return "\n".join(lines) + "\n"


def run_gpu(data: dict, source: str, out: Path) -> dict:
    """Run a gpu matrix into ``out`` (gpu.json, gpu.md); returns the result."""
    from engine.core.bvh import build_bvh
    from engine.core.offset import triangle_magnitudes
    from engine.gpu.device import device_name, require_cuda
    from engine.gpu.scene_upload import DeviceBVH, DeviceTriangles
    from scenes.catalog import load_named

    check_matrix(data, source)
    cuda = require_cuda()
    result = {"matrix": data.get("name", Path(source).stem), "device": device_name(),
              "date": time.strftime("%Y-%m-%d"), "labels": [v["label"] for v in data["variant"]],
              "rays": [], "frames": [], "images": [], "audits": []}
    out.mkdir(parents=True, exist_ok=True)
    for scene_table in data["scene"]:
        print(f"{scene_table['name']}:", flush=True)
        if scene_table.get("rays"):
            scene = load_named(scene_table["name"], dict(scene_table.get("params", {})))
            bvh = build_bvh(scene.triangles)
            tris_device = DeviceTriangles.from_host(scene.triangles, triangle_magnitudes(scene.triangles))
            result["rays"] += _scene_rays(scene_table, scene, bvh, data["variant"], data, cuda, tris_device,
                                          DeviceBVH.from_host(bvh, scene.triangles))
        if scene_table.get("recursion"):
            frames, images, audits = _frames(scene_table, data["variant"], data, source)
            result["frames"] += frames
            result["images"] += images
            result["audits"] += audits
        atomic.write_json(out / "gpu.json", result)  # after every scene: a cut-off run keeps its part
        atomic.write_text(out / "gpu.md", table(result))
    return result

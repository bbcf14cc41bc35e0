"""Dynamic-scene matrices: whole BART animation paths, BVH update policies against the
ray-space hierarchy (which has no scene structure to keep current).

A matrix with ``kind = "dynamic"`` (``packetrt bench benchmarks/bart-dynamic.toml``)::

    kind = "dynamic"
    name = "bart-dynamic"
    description = "..."
    threads = 0                     # numba threads (0 = every core)
    frames = 40                     # frames per path, evenly spaced over the whole path
    resolution = 1024               # or [W, H]
    packet = 16

    [[scene]]                       # one table per scene
    name = "bart-kitchen"           # a catalog scene, or path = "file.aff"
    recursion = "kitchen-paper"     # a preset of engine.bench.matrix.RECURSION
    params = {}                     # the scene's own parameters (lights = N is set by the preset)

    [[variant]]                     # one table per way of keeping up with the motion
    label = "bvh-auto"
    traversal = "paper"             # "paper" or a registered traversal for every kind
    frustum = "paper"               # "paper" or a registered frustum builder
    accel = "auto"                  # rebuild | refit | auto
    degrade = 1.2                   # auto's SAH threshold (optional)
    budget = 0.1                    # auto rebuilds while a build is at most this share of a frame
    frames = 4                      # optional: this variant's own frame count and resolution
    resolution = 256                # (the ray-space hierarchy is slow on a CPU)
    compare_fresh = true            # refit / auto (default): after each frame, its trace with the
                                    # kept tree against a fresh one, interleaved (min of 2 each)

Every (scene, variant) cell renders the path once in this process, warm (compile apart), and
appends one record to ``results.jsonl`` (``--resume`` skips finished cells). ``dynamic.md`` is
the table: mean FPS, the static FPS of the same frames (trace + shade of fresh trees: the frames
rendered as still scenes), the share of each frame spent keeping structures current, and, for
refit and auto, each frame's trace time on the kept tree over that on a tree freshly built for
the frame, both measured right after the frame, interleaved, fastest of two each.
"""
from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

from engine.bench import results
from engine.bench.figures import fmt, save, pyplot
from engine.bench.matrix import PAPER, RECURSION, check_labels
from engine.bench.machine import machine_info
from engine.core.atomic import output_folder, write_text
from engine.core.errors import ConfigError, PacketrtError
from engine.core.types import RAY_KINDS
from engine.core.threads import thread_count
from engine.render.animation import AnimationRenderer, path_summary, plan_times
from engine.render.config import from_dict
from scenes.catalog import entries, missing_file

TOP_KEYS = {"kind", "name", "description", "threads", "frames", "resolution", "packet", "scene", "variant"}
SCENE_KEYS = {"name", "path", "recursion", "params", "label"}
VARIANT_KEYS = {"label", "traversal", "frustum", "accel", "degrade", "budget", "frames", "resolution",
                "compare_fresh"}


def _fail(source, where, message):
    raise ConfigError(f"{source}: {where}: {message}")


def _table_list(source, data, key, allowed) -> list:
    tables = data.get(key)
    if not isinstance(tables, list) or not tables or not all(isinstance(t, dict) for t in tables):
        _fail(source, key, f"give one or more [[{key}]] tables")
    for i, table in enumerate(tables):
        unknown = set(table) - allowed
        if unknown:
            _fail(source, f"{key}[{i}]", f"unknown key(s) {sorted(unknown)}; allowed: {', '.join(sorted(allowed))}")
    return tables


def _scene_label(scene: dict) -> str:
    return str(scene.get("label") or scene.get("name") or Path(str(scene.get("path", "?"))).stem)


def _variant_label(variant: dict) -> str:
    """A variant's label, or its settings ("accel=refit") where it has none (messages said None)."""
    return str(variant.get("label") or ", ".join(f"{k}={v}" for k, v in variant.items() if k != "options")
               or "defaults")


def _per_kind(value, section) -> dict:
    if value == "paper":
        return dict(PAPER[section])
    return dict.fromkeys(RAY_KINDS, value)


def cell_config(matrix: dict, scene: dict, variant: dict, source: str):
    """The render Config of one (scene, variant) cell; mistakes name the matrix and key."""
    preset_name = scene.get("recursion", "kitchen-paper")
    if not isinstance(preset_name, str) or preset_name not in RECURSION:
        _fail(source, f"scene {_scene_label(scene)!r} recursion", f"unknown preset {preset_name!r}; "
              f"allowed: {', '.join(RECURSION)}")
    preset = RECURSION[preset_name]
    params = scene.get("params", {})
    if not isinstance(params, dict):
        _fail(source, f"scene {_scene_label(scene)!r} params", f"must be a table of the scene's parameters "
              f"(params = {{ lod = 3 }}), got {params!r}")
    params = dict(params)
    if "path" in scene and params:
        _fail(source, f"scene {_scene_label(scene)!r} params", "apply to catalog scenes only, not to a path")
    catalog = entries()
    if "name" in scene and scene["name"] not in catalog:
        _fail(source, f"scene {_scene_label(scene)!r}", f"unknown scene {scene['name']!r}; catalog scenes: "
              f"{', '.join(sorted(catalog))} (or give path = \"file.aff\")")
    if "path" in scene and not Path(scene["path"]).expanduser().is_file():
        _fail(source, f"scene {_scene_label(scene)!r}", f"scene file {scene['path']!r} "
              f"{missing_file(Path(scene['path']).expanduser())}")
    # The preset's light count goes to the scene's own `lights` parameter (the BART scenes').
    if not preset.lights or preset.max_lights is not None:
        entry = catalog.get(scene.get("name")) if "name" in scene else None
        if entry is None or "lights" not in entry.params:
            _fail(source, f"scene {_scene_label(scene)!r} recursion", f"preset {preset_name!r} sets how many "
                  f"lights cast shadows, which this scene cannot be told (it has no lights parameter); choose a "
                  f"preset that shades with every light")
        wanted = 0 if not preset.lights else preset.max_lights
        if "lights" in params and params["lights"] != wanted:  # the preset's count won without a word
            _fail(source, f"scene {_scene_label(scene)!r} params", f"lights = {params['lights']!r} clashes with "
                  f"preset {preset_name!r}, which shades with {wanted} light(s); leave lights out, or choose a "
                  f"preset that shades with every light (render-defaults, kitchen-full)")
        params["lights"] = wanted
    side = variant.get("resolution", matrix.get("resolution", 1024))
    sides = side if isinstance(side, list) else [side]  # load_dynamic checked: one or two integers
    width, height = (sides[0], sides[0]) if len(sides) == 1 else sides
    table = {
        "scene": {"path": scene["path"]} if "path" in scene else {"name": scene["name"], **params},
        "render": {"width": width, "height": height, "packet": matrix.get("packet", 16),
                   "threads": matrix.get("threads", 0), "max_depth": preset.max_depth,
                   "max_reflection_depth": preset.max_reflection_depth},
        "traversal": _per_kind(variant.get("traversal", "paper"), "traversal"),
        "frustum": _per_kind(variant.get("frustum", "paper"), "frustum"),
        "materials": {"override": preset.override},
        "accel": {"update": variant.get("accel", "rebuild"),
                  **{key: variant[key] for key in ("degrade", "budget") if key in variant}},
    }
    if variant.get("options"):  # per-plugin options, as a config's [options.NAME] tables
        table["options"] = dict(variant["options"])
    try:
        return from_dict(table, source=f"{source} scene {_scene_label(scene)!r} variant {_variant_label(variant)!r}")
    except ConfigError as exc:
        raise ConfigError(str(exc)) from None


def load_dynamic(data: dict, source: str) -> tuple[dict, list]:
    """(matrix table, [(cell id, scene table, variant table, Config)]) of a dynamic matrix,
    every cell's config checked before any work."""
    unknown = set(data) - TOP_KEYS
    if unknown:
        _fail(source, "top level", f"unknown key(s) {sorted(unknown)}; allowed: {', '.join(sorted(TOP_KEYS))}")
    for where, table in [("top level", data)] + [(f"variant[{i}]", v) for i, v in enumerate(data.get("variant") or [])
                                                 if isinstance(v, dict)]:
        frames = table.get("frames", 40)
        if isinstance(frames, bool) or not isinstance(frames, int) or not 1 <= frames <= 100_000:
            _fail(source, f"{where} frames", f"must be an integer in 1..100000, got {frames!r}")
        side = table.get("resolution", 1024)
        sides = [side] if not isinstance(side, list) else side
        if len(sides) not in (1, 2) or not all(isinstance(x, int) and not isinstance(x, bool) for x in sides):
            _fail(source, f"{where} resolution", f"must be an integer or [width, height], got {side!r}")
    cells, where = [], {}
    scenes, variants = _table_list(source, data, "scene", SCENE_KEYS), _table_list(source, data, "variant", VARIANT_KEYS)
    for kind, tables in (("scene", scenes), ("variant", variants)):
        labels = [t["label"] for t in tables if "label" in t]
        check_labels(source, kind, labels)
    for k, variant in enumerate(variants):
        if not isinstance(variant.get("compare_fresh", False), bool):
            _fail(source, f"variant[{k}] compare_fresh", f"must be true or false, got {variant['compare_fresh']!r}")
    for i, scene in enumerate(scenes):
        if ("name" in scene) == ("path" in scene):
            _fail(source, f"scene[{i}]", "give a catalog name or a path (one of them)")
        for key in ("name", "path"):
            if key in scene and not isinstance(scene[key], str):
                _fail(source, f"scene[{i}] {key}", f"must be a string, got {scene[key]!r}")
        for k, variant in enumerate(variants):
            config = cell_config(data, scene, variant, source)
            frames = variant.get("frames", data.get("frames", 40))
            identity = json.dumps({"config": config.to_dict(), "frames": frames}, sort_keys=True, default=str)
            cell_id = hashlib.sha1(identity.encode()).hexdigest()[:16]
            if cell_id in where:  # the same path twice: one record would stand for two rows
                _fail(source, f"scene[{i}] variant[{k}]", f"measures the same as {where[cell_id]}; give each "
                                                          f"cell its own settings")
            where[cell_id] = f"scene[{i}] variant[{k}]"
            cells.append((cell_id, scene, variant, config))
    return data, cells


def preflight(cells: list, source: str) -> None:
    """Open every distinct scene path of the cells once before any is measured, so that a scene
    file, parameter or light count the loader refuses is one line naming the matrix now, not
    after the cells before it ran."""
    from scenes.catalog import open_path

    seen = set()
    for _, scene, _, config in cells:
        key = (config.scene, config.override)
        if key in seen:
            continue
        seen.add(key)
        try:
            open_path(config.scene, config.override)
        except PacketrtError as exc:
            raise type(exc)(f"{source}: scene {_scene_label(scene)!r}: {exc}") from None


def run_cell(matrix: dict, scene: dict, variant: dict, config, cell_id: str, machine: dict) -> dict:
    """Render one cell's path; its record (path summary and per-frame records)."""
    from scenes.catalog import open_path

    started = time.time()
    path = open_path(config.scene, config.override)
    times = plan_times(path, frames=variant.get("frames", matrix.get("frames", 40)))
    animator = AnimationRenderer(path, config)
    compile_seconds = animator.warm_up(times[0])
    compare = variant.get("compare_fresh", config.accel.update in ("refit", "auto"))
    records = []
    for i, t in enumerate(times):
        frame = animator.frame(i, t)
        if compare and frame.record["accel"]["policy"] == "refit":
            animator.compare_with_fresh_tree(frame)   # after the frame: not in its time
        records.append(frame.record)
    summary = path_summary(records)
    return {
        "schema": 1, "kind": "dynamic", "id": cell_id, "matrix": matrix.get("name"),
        "labels": {"scene": _scene_label(scene), "variant": variant.get("label", "")},
        # The threads the kernels ran on (the config's 0 means every core: the table said "0 threads").
        "config": config.to_dict(), "threads": thread_count(config.render.threads), "frames": len(times),
        "seconds": {"compile": compile_seconds, "wall": time.time() - started}, "path": summary,
        "machine": machine,
    }


def _static_fps(record: dict) -> float:
    """Frames per second of the same frames without any structure update: trace + shade."""
    frames = record["path"]["frames"]
    return len(frames) / sum(f["seconds"]["trace"] + f["seconds"]["shade"] for f in frames)


def _same_frames(record: dict) -> tuple:
    """What makes two cells render the same frames: scene, traversal and frustum, image size,
    frame count and recursion. A refit row's static FPS comes from the rebuild row with the same
    key (it came from any rebuild row of the scene and plugins: an 8x8 one for a 64x64 refit)."""
    cfg = record["config"]
    return (record["labels"]["scene"], json.dumps(cfg["traversal"]), json.dumps(cfg["frustum"]),
            cfg["render"]["width"], cfg["render"]["height"], record["frames"], json.dumps(cfg.get("recursion")))


def table(records: list) -> str:
    """dynamic.md: one row per cell (see the module doc)."""
    fresh = {}
    for r in records:
        if r["config"]["accel"]["update"] == "rebuild":
            fresh[_same_frames(r)] = r
    lines = ["| scene | variant | size | frames | mean FPS | static FPS | FPS / static | accel share | scene share | "
             "accel ms (mean) | policies | trace / fresh tree, per frame (median, max) |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    for r in records:
        cfg, path = r["config"], r["path"]
        base = fresh.get(_same_frames(r))
        static = _static_fps(base if base is not None else r)
        accel_ms = 1000 * np.mean([f["seconds"]["accel"] for f in path["frames"]])
        ratio = "–"
        # Frames traced on a refitted tree, against a fresh tree at the same moment (rebuilt
        # frames are fresh trees: ratio 1).
        ratios = [f["fresh_tree"]["trace_ratio"] if "fresh_tree" in f else 1.0
                  for f in path["frames"] if "fresh_tree" in f or f["accel"]["policy"] == "rebuild"]
        if any("fresh_tree" in f for f in path["frames"]) and ratios:
            ratio = f"{np.median(ratios):.2f}, {max(ratios):.2f}"
        policies = ", ".join(f"{n} {p}" for p, n in path["policies"].items() if n)
        size = f"{cfg['render']['width']}x{cfg['render']['height']}"
        lines.append(f"| {r['labels']['scene']} | {r['labels']['variant']} | {size} | {r['frames']} | {fmt(path['mean_fps'])} | "
                     f"{fmt(static)} | {fmt(path['mean_fps'] / static)} | {100 * path['phase_share']['accel']:.1f}% | "
                     f"{100 * path['phase_share']['scene']:.1f}% | {accel_ms:.1f} | {policies} | {ratio} |")
    m = records[0]["machine"] if records else {}
    lines.append("")
    lines.append(f"{m.get('cpu', '?')}, {records[0]['threads'] if records else '?'} threads; "
                 f"one run, warm cache, compile time apart; commit {m.get('git', {}).get('commit', '?')[:10]}.")
    return "\n".join(lines) + "\n"


def plot(records: list, path: Path) -> None:
    """dynamic.png: per cell, mean milliseconds per frame stacked by phase."""
    plt = pyplot()
    phases = ("scene", "accel", "trace", "shade")
    fig, ax = plt.subplots(figsize=(max(6, 0.9 * len(records)), 4))
    labels = [f"{r['labels']['scene']}\n{r['labels']['variant']}" for r in records]
    bottom = np.zeros(len(records))
    for phase in phases:
        ms = np.array([1000 * np.mean([f["seconds"][phase] for f in r["path"]["frames"]]) for r in records])
        ax.bar(labels, ms, bottom=bottom, label=phase)
        bottom += ms
    ax.set_ylabel("ms per frame (mean over the path)")
    ax.legend(fontsize=8)
    ax.tick_params(axis="x", labelsize=7)
    save(fig, path)


def run_dynamic(data: dict, source: str, out: Path, resume: bool) -> dict:
    """Run every cell not yet in ``out/results.jsonl`` (all of them unless ``resume``), then
    write dynamic.md and dynamic.png; {"ran", "skipped", "files"}."""
    matrix, cells = load_dynamic(data, source)
    preflight(cells, source)  # before the output folder is made: a refused scene leaves nothing
    output_folder(out, "--out")
    file = out / results.RESULTS
    done = {r["id"] for r in results.read_results(file)[0]} if resume and file.exists() else set()
    if not resume and file.exists():
        raise ConfigError(f"{out} already holds results; give --resume to carry them on, or another --out")
    machine = machine_info()
    ran = 0
    for cell_id, scene, variant, config in cells:
        if cell_id in done:
            continue
        results.append(file, run_cell(matrix, scene, variant, config, cell_id, machine))
        ran += 1
    records = [r for r in results.read_results(file)[0] if r.get("kind") == "dynamic"]
    write_text(out / "dynamic.md", table(records))
    plot(records, out / "dynamic.png")
    return {"ran": ran, "skipped": len(cells) - ran, "files": [file, out / "dynamic.md", out / "dynamic.png"]}

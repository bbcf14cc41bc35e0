"""Benchmark matrices: a TOML file -> validated cells, before any work starts.

A matrix is the cross product of six axes::

    name = "smoke"              # default: the file's stem; names the default output folder
    description = "..."
    repeat = 2                  # timed repeats per cell (``--repeat`` overrides); default 5
    threads = 0                 # numba threads (0 = every core numba sees); Embree gets the same
    embree = true               # also time Embree on the same ray batches (ratios to Embree)
    open3d = true               # also time Open3D's RaycastingScene on them (default: embree's value)
    plot = ["mrays", "summary"] # figure kinds, see engine.bench.plots.PLOTS

    [axes]                      # every axis a non-empty list
    scene = ["whitted", {name = "bunny", lod = 3, label = "bunny-948"}]
    traversal = ["single", "paper", {label = "mixed", primary = "ranged", shadow = "masked"},
                 {label = "rs-pixel", shadow = "rayspace", options = {rayspace = {shadow_grid = "pixel"}}}]
    frustum = ["none", "paper"]
    packet = [8, 16]            # 2, 4, 8, 16, 32
    recursion = ["shadows", "reflection2"]   # keys of RECURSION
    resolution = [64, [128, 96], "256x128"]

    [[group]]                   # optional: each group is its own cross product of [axes]
    tag = "lod"                 # with the group's keys replacing them; plots select by tag
    scene = [...]

    [options.rayspace]          # per-plugin options, as in a render config
    pair_budget = 1000000

A traversal or frustum value is a registered plugin name (for every ray kind), ``"paper"`` (the
first paper's final system: Ranged primary, Partition others; pinhole / pointlight / general
frusta), or a table naming plugins per ray kind (kinds left out take the paper's choice) with
an optional ``label``; a traversal table may also carry ``options`` (tables per plugin, as
``[options]``), which override the matrix's options for its cells. A scene is a catalog name or a table ``{name, label, time, <params>}``.

Everything is checked here -- keys, types, plugin, scene and preset names, scene parameters and
data files, image sizes -- and a mistake is a ConfigError naming the file, the key (for example
``group[1].packet[0]``) and what is allowed.

Cells are identified by a hash of their full configuration (not of labels, tags or repeat
count), so ``--resume`` recognises a finished cell across edits that do not change it.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

from engine.render.config import (MAX_DEPTH, PAPER_FRUSTUM, PAPER_TRAVERSAL, Config, PerKind, RenderConfig, SceneConfig,
                     read_toml, validate)
from engine.core.errors import ConfigError, PacketrtError
from engine.packet.layout import PACKET_SIZES
from engine.core.types import RAY_KINDS


@dataclass(frozen=True)
class Recursion:
    """A ray-recursion configuration: how deep, whether point lights cast shadow rays (all of the
    scene's, or only its first ``max_lights`` in file order), and the material override
    (Overbeck et al. 2008, Section 5)."""

    max_depth: int
    lights: bool
    override: str
    max_reflection_depth: int = MAX_DEPTH
    doc: str = ""
    max_lights: int | None = None

    def as_dict(self) -> dict:
        # max_lights only when set: the cells of the other presets keep their hashes (--resume).
        return {"max_depth": self.max_depth, "max_reflection_depth": self.max_reflection_depth,
                "lights": self.lights, "override": self.override,
                **({} if self.max_lights is None else {"max_lights": self.max_lights})}


#: Named recursion presets. ``lights = False`` removes the scene's point lights: no shadow rays
#: (and ambient-only shading), so the figure isolates the other ray kinds; ``max_lights = N``
#: keeps the first N (the runner's ``cell_scene``; a scene with fewer is an error naming its count).
RECURSION = {
    "primary": Recursion(0, False, "none", doc="camera rays only"),
    "shadows": Recursion(0, True, "none", doc="camera rays + point-light shadows"),
    "reflection1": Recursion(1, False, "reflective", doc="1-bounce reflection, every material a mirror"),
    "reflection2": Recursion(2, False, "reflective", doc="2-bounce reflection, every material a mirror"),
    "refraction2": Recursion(2, False, "refractive", doc="2-deep refraction, every material glass"),
    "reflection1-shadows": Recursion(1, True, "reflective",
                                     doc="1-bounce reflection + shadows, every material a mirror"),
    "reflection1-native": Recursion(1, False, "none",
                                    doc="1 generation of reflection/refraction with the scene's own materials"),
    # The first paper's Table 2 configurations, with the scenes' own materials.
    "museum-reflect3": Recursion(3, False, "none", doc="BART Museum: 3-bounce reflections"),
    "kitchen-full": Recursion(4, True, "none", max_reflection_depth=1,
                              doc="BART Kitchen: 1-bounce reflections, 4-deep refractions, point-light shadows"),
    "kitchen-paper": Recursion(4, True, "none", max_reflection_depth=1, max_lights=1,
                               doc="the paper's Kitchen row: 1-bounce reflections, 4-deep refractions, "
                                   "shadows of the first point light only"),
    "bunny-floor": Recursion(1, False, "none", doc="bunny on a mirror floor: 1-bounce reflections"),
    "render-defaults": Recursion(5, True, "none", doc="packetrt render's defaults: 5 generations, every light"),
}

AXES = ("scene", "traversal", "frustum", "packet", "recursion", "resolution")
#: ASCII digits only: str.isdigit() also takes '²', which int() refuses.
_DECIMAL = re.compile(r"[0-9]+")
#: A matrix name: it names the default output folder (out/bench-NAME).
_FOLDER_NAME = re.compile(r"[A-Za-z0-9._-]{1,100}")
TOP_KEYS = ("name", "description", "repeat", "threads", "embree", "open3d", "plot", "axes", "group", "options",
            "paired")
#: Repetitions of a ``[paired]`` measurement when the table gives none (``engine.bench.paired_frames``).
DEFAULT_PAIRED_REPEAT = 21
PAPER = {"traversal": PAPER_TRAVERSAL, "frustum": PAPER_FRUSTUM}
DEFAULT_REPEAT = 5
MAX_REPEAT = 1000


@dataclass(frozen=True)
class SceneSpec:
    """A catalog scene with parameters: params is ((key, value), ...) sorted."""

    name: str
    params: tuple = ()
    time: float = 0.0
    label: str = ""

    def identity(self) -> dict:
        return {"name": self.name, "params": dict(self.params), "time": self.time}


@dataclass(frozen=True)
class PluginSpec:
    """Plugin names per ray kind (in RAY_KINDS order) and a label for tables and plots."""

    label: str
    names: tuple
    #: Plugin options of this traversal entry, ((plugin, ((key, value), ...)), ...): they
    #: override the matrix's [options] for its cells, so one matrix can compare option values.
    options: tuple = ()

    def per_kind(self) -> dict:
        return dict(zip(RAY_KINDS, self.names))


@dataclass(frozen=True)
class Cell:
    """One measurement: a scene, plugins, packet size, recursion preset and image size."""

    scene: SceneSpec
    traversal: PluginSpec
    frustum: PluginSpec
    packet: int
    recursion: str
    width: int
    height: int
    threads: int = 0
    embree: bool = True
    options: tuple = ()
    tags: tuple = ()
    open3d: bool = False

    @property
    def preset(self) -> Recursion:
        return RECURSION[self.recursion]

    def identity(self) -> dict:
        """The full configuration that defines this cell (what its hash is of)."""
        return {"scene": self.scene.identity(), "traversal": self.traversal.per_kind(),
                "frustum": self.frustum.per_kind(), "packet": self.packet,
                "recursion": {"name": self.recursion, **self.preset.as_dict()},
                "width": self.width, "height": self.height, "threads": self.threads,
                "options": {name: dict(opts) for name, opts in self.options}, "embree": self.embree,
                # open3d only when on: cells measured without it keep their ids (--resume).
                **({"open3d": True} if self.open3d else {})}

    @property
    def key(self) -> str:
        """Stable 16-hex-digit id: sha1 of the canonical JSON of ``identity()``."""
        text = json.dumps(self.identity(), sort_keys=True, separators=(",", ":"), default=str)
        return hashlib.sha1(text.encode()).hexdigest()[:16]

    def labels(self) -> dict:
        return {"scene": self.scene.label, "traversal": self.traversal.label, "frustum": self.frustum.label,
                "recursion": self.recursion, "packet": self.packet, "resolution": f"{self.width}x{self.height}"}

    def config(self) -> Config:
        """The render Config of this cell (scene lights are the bench's business, not the config's)."""
        p = self.preset
        render = RenderConfig(width=self.width, height=self.height, max_depth=p.max_depth, packet=self.packet,
                              threads=self.threads, max_reflection_depth=p.max_reflection_depth)
        return Config(scene=SceneConfig(name=self.scene.name, time=self.scene.time, params=self.scene.params),
                      render=render, traversal=PerKind(*self.traversal.names), frustum=PerKind(*self.frustum.names),
                      override=p.override, options=self.options, source="<bench>")

    def describe(self) -> str:
        return (f"{self.scene.label} {self.recursion} {self.width}x{self.height} {self.traversal.label}/"
                f"{self.frustum.label} {self.packet}x{self.packet}")


@dataclass
class Matrix:
    name: str
    description: str
    source: str
    repeat: int
    threads: int
    embree: bool
    plots: tuple
    cells: list = field(default_factory=list)
    open3d: bool = False
    #: ``[paired]``: ((traversal PluginSpec, frustum PluginSpec, packet), ...) rendered frame by
    #: frame against the first for every (scene, recursion, size) of the cells, and its repetitions.
    paired: tuple = ()
    paired_repeat: int = 0
    #: The matrix's own ``[options]`` (a cell's are these merged with its traversal entry's).
    options: tuple = ()


# -- parsing ------------------------------------------------------------------------------

def _fail(source: str, where: str, message: str):
    raise ConfigError(f"{source}: {where}: {message}")


def check_matrix_name(source: str, name) -> None:
    """A matrix's ``name`` names its default output folder (out/bench-NAME): 1-100 letters,
    digits, '.', '-' or '_', so it can neither climb out of out/ nor be empty. Every matrix kind."""
    if not isinstance(name, str) or not _FOLDER_NAME.fullmatch(name) or name in (".", ".."):
        _fail(source, "name", f"must be 1-100 letters, digits, '.', '-' or '_' (it names the output folder), "
                              f"got {name!r}")


def check_labels(source: str, where: str, labels: list) -> None:
    """Each of ``labels`` a table row's name (``check_label``), none twice."""
    for i, label in enumerate(labels):
        check_label(source, f"{where}[{i}].label", label)
        if label in labels[:i]:
            _fail(source, f"{where}[{i}].label", f"{label!r} is already the label of {where}[{labels.index(label)}]; "
                                                 f"give each its own")


def check_label(source: str, where: str, label) -> None:
    """A label names a row of the Markdown tables and a series of the plots: a string of 1 to 80
    printable characters, none of them '|' (a table's column break)."""
    if not isinstance(label, str):
        _fail(source, where, f"must be a string, got {label!r}")
    if not 1 <= len(label) <= 80 or not label.isprintable() or "|" in label:
        _fail(source, where, f"must be 1 to 80 printable characters without '|', got {label!r}")


def _type_name(value) -> str:
    return type(value).__name__


def _int(source, where, value, allowed: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        _fail(source, where, f"must be an integer ({allowed}), got {value!r} ({_type_name(value)})")
    return value


def _plugin(source, where, value, what: str) -> PluginSpec:
    from engine.render.plugins import frustum_names, traversal_names

    known = traversal_names() if what == "traversal" else frustum_names()
    allowed = f"{', '.join(known)}, paper, or a table of ray kinds ({', '.join(RAY_KINDS)}) and label"

    def check(name, key):
        if not isinstance(name, str):
            _fail(source, key, f"must be a {what} name ({allowed}), got {name!r} ({_type_name(name)})")
        if name not in known:
            _fail(source, key, f"unknown {what} {name!r}; registered {what}s: {', '.join(known)}")
        return name

    if isinstance(value, str):
        if value == "paper":
            return PluginSpec("paper", tuple(check(PAPER[what][k], where) for k in RAY_KINDS))
        return PluginSpec(value, (check(value, where),) * len(RAY_KINDS))
    if isinstance(value, dict):
        extra = {"label", "options"} if what == "traversal" else {"label"}
        unknown = set(value) - set(RAY_KINDS) - extra
        if unknown:
            _fail(source, where, f"unknown key(s) {sorted(unknown)}; allowed: {', '.join(RAY_KINDS)}, "
                                 f"{', '.join(sorted(extra))}")
        names = tuple(check(value.get(k, PAPER[what][k]), f"{where}.{k}") for k in RAY_KINDS)
        label = value.get("label", ",".join(f"{k}={value[k]}" for k in RAY_KINDS if k in value) or "paper")
        check_label(source, f"{where}.label", label)
        return PluginSpec(label, names, _options(source, f"{where}.options", value.get("options", {})))
    _fail(source, where, f"must be a {what} name or a table ({allowed}), got {value!r} ({_type_name(value)})")


def _options(source, where, value) -> tuple:
    """((plugin, ((key, value), ...)), ...), sorted, of a table of per-plugin option tables."""
    if not isinstance(value, dict) or not all(isinstance(v, dict) for v in value.values()):
        _fail(source, where, "must be tables of plugin options (PLUGIN = {key = value})")
    return tuple((plugin, tuple(sorted(table.items()))) for plugin, table in sorted(value.items()))


def merged_options(base: tuple, own: tuple) -> tuple:
    """``base`` options with ``own``'s keys replacing or joining them, plugin by plugin."""
    tables = {plugin: dict(items) for plugin, items in base}
    for plugin, items in own:
        tables.setdefault(plugin, {}).update(items)
    return tuple((plugin, tuple(sorted(table.items()))) for plugin, table in sorted(tables.items()))


def parse_variant(text, source: str, where: str) -> tuple:
    """(traversal PluginSpec, frustum PluginSpec, packet) of a "TRAVERSAL/FRUSTUM/PACKET" string
    (plugin names or "paper", a packet size); a ConfigError naming ``source`` and ``where``."""
    from engine.packet.layout import PACKET_SIZES

    parts = text.split("/") if isinstance(text, str) else []
    if len(parts) != 3 or not _DECIMAL.fullmatch(parts[2]) or int(parts[2]) not in PACKET_SIZES:
        _fail(source, where, f"expected TRAVERSAL/FRUSTUM/PACKET with a packet size in "
                             f"{', '.join(map(str, PACKET_SIZES))}, got {text!r}")
    return _plugin(source, where, parts[0], "traversal"), _plugin(source, where, parts[1], "frustum"), int(parts[2])


def _scene(source, where, value) -> SceneSpec:
    from scenes.catalog import entries

    catalog = entries()
    allowed = ", ".join(sorted(catalog))
    if isinstance(value, str):
        table = {"name": value}
    elif isinstance(value, dict):
        table = dict(value)
    else:
        _fail(source, where, f"must be a catalog scene name or a table {{name, label, time, <params>}} "
                             f"(scenes: {allowed}), got {value!r} ({_type_name(value)})")
    name = table.pop("name", None)
    if not isinstance(name, str):
        _fail(source, f"{where}.name", f"must be a catalog scene name ({allowed}), got {name!r}")
    if name not in catalog:
        _fail(source, where, f"unknown scene {name!r}; catalog scenes: {allowed}")
    label = table.pop("label", None)
    time = table.pop("time", 0.0)
    if isinstance(time, bool) or not isinstance(time, (int, float)):
        _fail(source, f"{where}.time", f"must be a number, got {time!r}")
    entry = catalog[name]
    unknown = set(table) - set(entry.params)
    if unknown:
        _fail(source, where, f"scene {name!r} has no parameter(s) {sorted(unknown)}; "
                             f"allowed: {', '.join(sorted(entry.params)) or 'none'}, label, time")
    for key, val in table.items():
        default = entry.params[key]
        numeric = isinstance(default, (int, float)) and not isinstance(default, bool)
        if default == "all" and isinstance(val, int) and not isinstance(val, bool):
            continue  # a count where the default is "all" (the BART scenes' lights); the loader checks it
        if numeric and (isinstance(val, bool) or not isinstance(val, (int, float))) or \
                not numeric and type(val) is not type(default):
            _fail(source, f"{where}.{key}", f"must be {_type_name(default)} like the default {default!r}, "
                                            f"got {val!r} ({_type_name(val)})")
    if label is None:
        label = name + ("(" + ",".join(f"{k}={v}" for k, v in sorted(table.items())) + ")" if table else "")
    else:
        check_label(source, f"{where}.label", label)
    return SceneSpec(name, tuple(sorted(table.items())), float(time), label)


def _resolution(source, where, value) -> tuple:
    allowed = "N (N x N), [W, H] or \"WxH\""
    if isinstance(value, int) and not isinstance(value, bool):
        return value, value
    if isinstance(value, list) and len(value) == 2 and all(isinstance(v, int) and not isinstance(v, bool)
                                                          for v in value):
        return tuple(value)
    if isinstance(value, str):
        w, sep, h = value.lower().partition("x")
        if sep and _DECIMAL.fullmatch(w) and _DECIMAL.fullmatch(h):
            return int(w), int(h)
    _fail(source, where, f"must be {allowed}, got {value!r} ({_type_name(value)})")


def _axis_value(source, where, axis, value):
    if axis == "scene":
        return _scene(source, where, value)
    if axis in ("traversal", "frustum"):
        return _plugin(source, where, value, axis)
    if axis == "packet":
        allowed = ", ".join(map(str, PACKET_SIZES))
        n = _int(source, where, value, f"one of {allowed}")
        if n not in PACKET_SIZES:
            _fail(source, where, f"packet size must be one of {allowed}, got {n}")
        return n
    if axis == "recursion":
        allowed = ", ".join(RECURSION)
        if not isinstance(value, str):
            _fail(source, where, f"must be a recursion preset name ({allowed}), got {value!r} ({_type_name(value)})")
        if value not in RECURSION:
            _fail(source, where, f"unknown recursion preset {value!r}; allowed: {allowed}")
        return value
    return _resolution(source, where, value)


def _axes(source, table: dict, where: str, required: bool) -> dict:
    """{axis: [parsed values]} for the axis keys of ``table``."""
    parsed = {}
    for axis in AXES:
        if axis not in table:
            if required:
                _fail(source, f"{where}{axis}", f"missing axis; every cell needs {', '.join(AXES)}")
            continue
        values = table[axis]
        if not isinstance(values, list):
            values = [values]
        if not values:
            hint = {"packet": f"one of {', '.join(map(str, PACKET_SIZES))}", "recursion": ", ".join(RECURSION)}
            _fail(source, f"{where}{axis}", "axis is empty; give at least one value"
                                            + (f" ({hint[axis]})" if axis in hint else ""))
        parsed[axis] = [_axis_value(source, f"{where}{axis}[{i}]", axis, v) for i, v in enumerate(values)]
        labels = [getattr(v, "label", None) for v in parsed[axis]]
        for i, label in enumerate(labels):
            if label is not None and label in labels[:i]:  # two rows of a table or plot would read alike
                _fail(source, f"{where}{axis}[{i}]", f"label {label!r} is already that of {axis}[{labels.index(label)}]; "
                                                     f"give each value its own label")
    return parsed


def parse_matrix(data: dict, source: str = "<matrix>", repeat: int | None = None) -> Matrix:
    """Matrix from a parsed TOML table; every key and every cell is checked (ConfigError)."""
    from engine.bench.plots import PLOTS

    unknown = set(data) - set(TOP_KEYS)
    if unknown:
        _fail(source, ", ".join(sorted(unknown)), f"unknown key(s); allowed: {', '.join(TOP_KEYS)}")
    name = data.get("name", Path(source).stem)
    description = data.get("description", "")
    for key, value in (("name", name), ("description", description)):
        if not isinstance(value, str):
            _fail(source, key, f"must be a string, got {value!r}")
    check_matrix_name(source, name)
    if repeat is None:
        repeat = _int(source, "repeat", data.get("repeat", DEFAULT_REPEAT), f"1..{MAX_REPEAT}")
        where = "repeat"
    else:
        where = "--repeat"
    if isinstance(repeat, bool) or not isinstance(repeat, int) or not 1 <= repeat <= MAX_REPEAT:
        _fail(source, where, f"must be in 1..{MAX_REPEAT}, got {repeat!r}")
    threads = _int(source, "threads", data.get("threads", 0), "0 = all cores, or 1..1024")
    embree = data.get("embree", True)
    if not isinstance(embree, bool):
        _fail(source, "embree", f"must be true or false, got {embree!r}")
    open3d = data.get("open3d", embree)
    if not isinstance(open3d, bool):
        _fail(source, "open3d", f"must be true or false, got {open3d!r}")
    plots = data.get("plot", ["summary"])
    if not isinstance(plots, list) or not all(isinstance(p, str) for p in plots):
        _fail(source, "plot", f"must be a list of figure kinds ({', '.join(PLOTS)}), got {plots!r}")
    for i, kind in enumerate(plots):
        if kind not in PLOTS:
            _fail(source, f"plot[{i}]", f"unknown figure kind {kind!r}; allowed: {', '.join(PLOTS)}")
    options = _options(source, "options", data.get("options", {}))
    axes = data.get("axes", {})
    if not isinstance(axes, dict):
        _fail(source, "axes", f"must be a table of axes ({', '.join(AXES)})")
    unknown = set(axes) - set(AXES)
    if unknown:
        key = sorted(unknown)[0]
        hint = " (top-level keys go before [axes])" if key in TOP_KEYS else ""
        _fail(source, f"axes.{key}", f"unknown axis; allowed: {', '.join(AXES)}{hint}")
    groups = data.get("group", [{}])
    if not isinstance(groups, list) or not groups or not all(isinstance(g, dict) for g in groups):
        _fail(source, "group", "must be a non-empty array of tables [[group]]")
    base = _axes(source, axes, "axes.", required=False)
    cells: dict = {}
    # A label names one scene, traversal or frustum across the whole matrix: the same label on
    # two different entries of two groups made tables merge or drop their cells.
    named: dict = {}
    for g, group in enumerate(groups):
        where = f"group[{g}]." if "group" in data else "axes."
        unknown = set(group) - set(AXES) - {"tag"}
        if unknown:
            _fail(source, f"{where}{sorted(unknown)[0]}", f"unknown key; allowed: {', '.join(AXES)}, tag")
        tag = group.get("tag", "")
        if not isinstance(tag, str):
            _fail(source, f"{where}tag", f"must be a string, got {tag!r}")
        own = _axes(source, group, where, required=False)
        merged = {**base, **own}
        for axis in ("scene", "traversal", "frustum"):
            for spec in merged.get(axis, []):
                earlier = named.setdefault((axis, spec.label), spec)
                if earlier != spec:
                    _fail(source, f"{where}{axis}", f"label {spec.label!r} already names another {axis} of this "
                                                    f"matrix; give each its own label")
        missing = [a for a in AXES if a not in merged]
        if missing:
            _fail(source, f"{where}{missing[0]}", f"missing axis (in [axes] or the group); every cell needs "
                                                  f"{', '.join(AXES)}")
        for scene, trav, frus, packet, rec, (w, h) in itertools.product(*(merged[a] for a in AXES)):
            cell = Cell(scene, trav, frus, packet, rec, w, h, threads, embree, merged_options(options, trav.options),
                        (tag,) if tag else (), open3d=open3d)
            _check_cell(source, where, cell)
            previous = cells.get(cell.key)
            if previous is not None:  # the same measurement asked twice: run it once, keep both tags
                tags = tuple(dict.fromkeys(previous.tags + cell.tags))
                cell = Cell(**{**previous.__dict__, "tags": tags})
            cells[cell.key] = cell
    _check_scene_files(source, cells.values())
    # Cells of one scene run together (one scene loaded at a time); scenes and presets keep the
    # order the matrix gives them, which the plots' rows and columns follow.
    first = {}
    for cell in cells.values():
        first.setdefault(("scene", cell.scene.name, cell.scene.params, cell.scene.time), len(first))
        first.setdefault(("recursion", cell.recursion), len(first))
    ordered = sorted(cells.values(), key=lambda c: (first["scene", c.scene.name, c.scene.params, c.scene.time],
                                                     first["recursion", c.recursion], c.width * c.height, c.packet))
    paired, paired_repeat = _paired(source, data.get("paired"))
    return Matrix(name, description, source, repeat, threads, embree, tuple(plots), ordered, open3d, paired,
                  paired_repeat, options)


def _paired(source: str, table) -> tuple:
    """((traversal, frustum, packet) per variant, repeat) of a ``[paired]`` table, or ((), 0).

    [paired]
    variants = ["simd/none/2", "paper/paper/16"]   # TRAVERSAL/FRUSTUM/PACKET, two or more; the first
                                                   # is the one the others are divided by
    repeat = 21                                    # paired repetitions (engine.bench.paired_frames)
    """
    if table is None:
        return (), 0
    if not isinstance(table, dict):
        _fail(source, "paired", "must be a table [paired] with variants = [...] and repeat")
    unknown = set(table) - {"variants", "repeat"}
    if unknown:
        _fail(source, f"paired.{sorted(unknown)[0]}", "unknown key; allowed: variants, repeat")
    variants = table.get("variants")
    if not isinstance(variants, list) or len(variants) < 2 or not all(isinstance(v, str) for v in variants):
        _fail(source, "paired.variants", f"must list two or more \"TRAVERSAL/FRUSTUM/PACKET\" strings, got {variants!r}")
    parsed = [parse_variant(text, source, f"paired.variants[{i}]") for i, text in enumerate(variants)]
    repeat = _int(source, "paired.repeat", table.get("repeat", DEFAULT_PAIRED_REPEAT), f"1..{MAX_REPEAT}")
    if not 1 <= repeat <= MAX_REPEAT:
        _fail(source, "paired.repeat", f"must be in 1..{MAX_REPEAT}, got {repeat}")
    return tuple(parsed), repeat


def _check_cell(source: str, where: str, cell: Cell) -> None:
    """The render config's own checks (sizes, memory, plugin options) for one cell."""
    try:
        validate(cell.config())
    except ConfigError as exc:
        _fail(source, f"{where.rstrip('.')} cell {cell.describe()}", str(exc))


def _check_scene_files(source: str, cells) -> None:
    """Every scene's data files are on the search path (named when missing)."""
    from scenes.catalog import entries, find_files, missing_message

    catalog = entries()
    seen = set()
    for cell in cells:
        spec = cell.scene
        if (spec.name, spec.params) in seen:
            continue
        seen.add((spec.name, spec.params))
        try:
            _, missing = find_files(catalog[spec.name], dict(spec.params))
        except PacketrtError as exc:
            _fail(source, f"scene {spec.label}", str(exc))
        if missing:
            _fail(source, f"scene {spec.label}", missing_message(spec.name, missing))


def load_matrix(path: str, repeat: int | None = None) -> Matrix:
    """Matrix from a TOML file; a missing or malformed file or any bad key is a ConfigError."""
    return parse_matrix(read_toml(path, "matrix"), source=str(path), repeat=repeat)

"""Render configuration: TOML parsed into frozen dataclasses.

::

    [scene]      name = "whitted"        # or path = "my.obj"; time = 0.0; other keys are the
                                         # scene's own parameters (e.g. lod = 2 for "bunny")
    [render]     width = 512  height = 512  max_depth = 5  packet = 16  threads = 0  device = "cpu"
                 leaf_size = 4  bins = 16
                 max_reflection_depth = 64   # mirror reflections only off hits of depth < this
                 shadow_order = "auto"  # walk shadow rays from the "surface" end, the "light" end, or
                                        # "auto": per light, the end its trials visited fewer nodes
                                        # from (the GPU, which has no trials: the light end)
    [traversal]  primary = "ranged"  shadow = "partition"  reflection = "partition"  refraction = "partition"
    [frustum]    primary = "pinhole" shadow = "pointlight" reflection = "general"    refraction = "general"
    [materials]  override = "none"       # or "reflective" / "refractive"
    [plugins]    load_entry_points = false
    [accel]      update = "rebuild"      # per animation frame: "rebuild" | "refit" | "auto"
                 degrade = 1.2           # auto: rebuild past this SAH cost over the last build's
                 budget = 0.1            # auto: rebuild while a build takes <= this share of a frame
    [options.rayspace]  pair_budget = 4194304   # per-plugin options, checked by the plugin

An unknown section, key or plugin name is a ConfigError that says what is allowed.
``threads = 0`` means every core numba sees.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from engine.core import checked
from engine.core.errors import ConfigError, ConfigTypeError
from engine.packet.layout import PACKET_SIZES, check_packet_size
from engine.core.types import RAY_KINDS
from engine.render.shadow_order import SHADOW_ORDERS

#: The first paper's final system (Overbeck et al. 2008, Section 6), when its plugins exist.
PAPER_TRAVERSAL = {"primary": "ranged", "shadow": "partition", "reflection": "partition", "refraction": "partition"}
PAPER_FRUSTUM = {"primary": "pinhole", "shadow": "pointlight", "reflection": "general", "refraction": "general"}
MAX_IMAGE_SIDE = 16384
MAX_DEPTH = 64
DEVICES = ("cpu", "cuda")
#: Animation times in seconds: any finite time within a day either way.
MAX_TIME = 86400.0
#: The allowed range of each integer of [render] (threads 0 = all cores; leaf_size and bins
#: as the BVH builder takes them).
RENDER_RANGES = {"width": (1, MAX_IMAGE_SIDE), "height": (1, MAX_IMAGE_SIDE), "max_depth": (0, MAX_DEPTH),
                 "max_reflection_depth": (0, MAX_DEPTH), "threads": (0, 1024), "leaf_size": (1, 255),
                 "bins": (2, 256)}
#: Peak working memory per pixel of one wavefront (ray batch, hits, shading temporaries).
BYTES_PER_PIXEL = 600


def available_memory() -> int:
    """Bytes of memory a new allocation can get now: Linux's MemAvailable (free memory plus
    what the page cache would give back), not the machine's total -- a render that fits the
    total but not what is free would die with a MemoryError. Elsewhere the free pages, and a
    generous 64 GiB guess where the OS will not say."""
    import os

    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 64 * 2**30


@dataclass(frozen=True)
class SceneConfig:
    name: str = "whitted"
    path: str = ""
    time: float = 0.0
    params: tuple = ()  # ((key, value), ...): the scene's own parameters


@dataclass(frozen=True)
class RenderConfig:
    width: int = 512
    height: int = 512
    max_depth: int = 5
    packet: int = 16
    threads: int = 0
    leaf_size: int = 4
    bins: int = 16
    # Mirror reflections spawn only off hits at depth < this (and < max_depth): the papers'
    # "1-bounce reflections, 4-deep refractions" is max_depth = 4, max_reflection_depth = 1.
    max_reflection_depth: int = MAX_DEPTH
    # "cpu" (numba kernels on every core) or "cuda" (``engine.gpu``: the wavefront frame on a GPU).
    device: str = "cpu"
    # Which end of their segments shadow rays are walked from (``engine.render.shadow_order``):
    # "surface", "light" or "auto". Answers and images are the same either way; only speed differs.
    shadow_order: str = "auto"


@dataclass(frozen=True)
class AccelConfig:
    """How ``packetrt animate`` keeps the BVH current (``engine.render.accel``)."""

    update: str = "rebuild"
    degrade: float = 1.2
    budget: float = 0.1


def _defaults(table: dict) -> dict:
    """The paper's choice where that plugin is registered, else the reference ``single``/``none``."""
    from engine.render.plugins import frustum_names, traversal_names

    known = traversal_names() if table is PAPER_TRAVERSAL else frustum_names()
    fallback = "single" if table is PAPER_TRAVERSAL else "none"
    return {kind: (name if name in known else fallback) for kind, name in table.items()}


@dataclass(frozen=True)
class PerKind:
    primary: str
    shadow: str
    reflection: str
    refraction: str

    def get(self, kind: str) -> str:
        return getattr(self, kind)


@dataclass(frozen=True)
class Config:
    scene: SceneConfig = field(default_factory=SceneConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    traversal: PerKind = None
    frustum: PerKind = None
    override: str = "none"
    load_entry_points: bool = False
    options: tuple = ()  # ((plugin name, ((key, value), ...)), ...)
    source: str = "<defaults>"
    accel: AccelConfig = field(default_factory=AccelConfig)

    def __post_init__(self):
        if self.traversal is None:
            object.__setattr__(self, "traversal", PerKind(**_defaults(PAPER_TRAVERSAL)))
        if self.frustum is None:
            object.__setattr__(self, "frustum", PerKind(**_defaults(PAPER_FRUSTUM)))

    def to_dict(self) -> dict:
        return {
            "scene": {"name": self.scene.name, "path": self.scene.path, "time": self.scene.time,
                      **dict(self.scene.params)},
            "render": {f.name: getattr(self.render, f.name) for f in fields(RenderConfig)},
            "traversal": {k: self.traversal.get(k) for k in RAY_KINDS},
            "frustum": {k: self.frustum.get(k) for k in RAY_KINDS},
            "materials": {"override": self.override},
            "plugins": {"load_entry_points": self.load_entry_points},
            "options": {name: dict(opts) for name, opts in self.options},
            "accel": {f.name: getattr(self.accel, f.name) for f in fields(AccelConfig)},
        }


def _check_type(where: str, key: str, value, expected):
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if expected is int and isinstance(value, bool) or not isinstance(value, expected):
        raise ConfigError(f"{where}: {key} must be {expected.__name__}, got {value!r}")
    return value


def _dataclass_from(cls, table: dict, where: str):
    allowed = {f.name: f.type for f in fields(cls)}
    kwargs = {}
    for key, value in table.items():
        if key not in allowed:
            raise ConfigError(f"{where}: unknown key {key!r}; allowed: {', '.join(allowed)}")
        expected = {"int": int, "str": str, "float": float, "bool": bool}[allowed[key]]
        kwargs[key] = _check_type(where, key, value, expected)
    return cls(**kwargs)


def _checked_structure(config: Config) -> Config:
    """``config`` with each part of its own type (a Config built by hand in Python may hold
    anything: render=None, traversal="single", packet=8.0) and its integers plain ints (numpy
    integers would reach the --stats JSON); else a ConfigTypeError naming the field."""
    if not isinstance(config, Config):
        raise ConfigTypeError(f"expected a packetrt Config, got {type(config).__name__}")
    parts = {"scene": SceneConfig, "render": RenderConfig, "traversal": PerKind, "frustum": PerKind,
             "accel": AccelConfig}
    for name, kind in parts.items():
        if not isinstance(getattr(config, name), kind):
            raise ConfigTypeError(f"Config.{name} must be of type {kind.__name__}, got {getattr(config, name)!r}")
    for name, kind in (("override", str), ("load_entry_points", bool), ("options", tuple), ("source", str)):
        if not isinstance(getattr(config, name), kind):
            raise ConfigTypeError(f"Config.{name} must be of type {kind.__name__}, got {getattr(config, name)!r}")
    for name, options in config.options:
        if not isinstance(name, str) or not isinstance(options, tuple):
            raise ConfigTypeError(f"Config.options must be ((plugin name, ((key, value), ...)), ...), got "
                                  f"{config.options!r}")
    for kind in RAY_KINDS:
        for part in ("traversal", "frustum"):
            if not isinstance(getattr(config, part).get(kind), str):
                raise ConfigTypeError(f"{part}.{kind} must be a plugin name, got {getattr(config, part).get(kind)!r}")
    for name in ("name", "path"):
        if not isinstance(getattr(config.scene, name), str):
            raise ConfigTypeError(f"scene.{name} must be a string, got {getattr(config.scene, name)!r}")
    if not isinstance(config.scene.params, tuple):
        raise ConfigTypeError(f"scene.params must be ((key, value), ...), got {config.scene.params!r}")
    for name in ("device", "shadow_order"):
        if not isinstance(getattr(config.render, name), str):
            raise ConfigTypeError(f"render.{name} must be a string, got {getattr(config.render, name)!r}")
    integers = {key: checked.to_int(getattr(config.render, key), f"render.{key}", lo, hi)
                for key, (lo, hi) in RENDER_RANGES.items()}
    integers["packet"] = check_packet_size(config.render.packet)
    return replace(config, render=replace(config.render, **integers))


def validate(config: Config) -> Config:
    """Range and name checks shared by files and command-line overrides; returns the config
    (its integers made plain ints)."""
    config = _checked_structure(config)
    r = config.render
    needed = r.width * r.height * BYTES_PER_PIXEL
    free = available_memory()
    if needed > free:
        raise ConfigError(f"render size {r.width}x{r.height} needs about {needed / 2**30:.1f} GiB for its ray "
                          f"batches, more than this machine's {free / 2**30:.1f} GiB of memory available now; render smaller")
    checked.to_float(config.scene.time, "scene.time", -MAX_TIME, MAX_TIME)
    if r.device not in DEVICES:
        raise ConfigError(f"render.device must be one of {', '.join(DEVICES)}, got {r.device!r}")
    if r.shadow_order not in SHADOW_ORDERS:
        raise ConfigError(f"render.shadow_order must be one of {', '.join(SHADOW_ORDERS)}, got {r.shadow_order!r}")
    if config.accel.update not in ("rebuild", "refit", "auto"):
        raise ConfigError(f"accel.update must be 'rebuild', 'refit' or 'auto', got {config.accel.update!r}")
    checked.to_float(config.accel.degrade, "accel.degrade", 1.0, 100.0)
    if config.accel.degrade <= 1.0:
        raise ConfigError(f"accel.degrade must be above 1 (a SAH cost ratio), got {config.accel.degrade!r}")
    checked.to_float(config.accel.budget, "accel.budget", 0.0, 1.0)
    if config.override not in ("none", "reflective", "refractive"):
        raise ConfigError(f"materials.override must be 'none', 'reflective' or 'refractive', got {config.override!r}")
    from engine.render.plugins import configured, frustum_names, load_entry_points, make_traversal, traversal_names

    if config.load_entry_points:
        load_entry_points()
    if r.device == "cuda":
        # Device traversals are chosen by name too (``engine.gpu.traversals``): check the names
        # here without importing CUDA; whether a GPU is there is asked when rendering starts.
        from engine.render.device_names import device_traversal_name

        for kind in RAY_KINDS:
            device_traversal_name(config.traversal.get(kind), kind)
        return config
    # Throwaway instances: building them checks names, keys and values; nothing is kept.
    configured(config)
    for name, options in config.options:
        if name in frustum_names() and name not in traversal_names():
            raise ConfigError(f"[options.{name}]: {name!r} is a frustum builder, and frustum builders take no "
                              f"options; [options.NAME] configures traversals ({', '.join(traversal_names())})")
        make_traversal(name, dict(options))
    return config


def from_dict(data: dict, source: str = "<dict>") -> Config:
    """Config from a parsed TOML table; every key is checked."""
    sections = {"scene", "render", "traversal", "frustum", "materials", "plugins", "options", "accel"}
    unknown = set(data) - sections
    if unknown:
        raise ConfigError(f"{source}: unknown section(s) {sorted(unknown)}; allowed: {', '.join(sorted(sections))}")
    for section in sections & set(data):
        if not isinstance(data[section], dict):
            raise ConfigError(f"{source}: [{section}] must be a table")
    scene_table = dict(data.get("scene", {}))
    if source != "<dict>" and "path" in scene_table:  # a written config; a dict may be a to_dict() round trip
        if isinstance(scene_table["path"], str) and not scene_table["path"].strip():
            raise ConfigError(f"{source} [scene]: path is empty; give a scene file, or leave path out for a "
                              f"catalog name")
        if "name" in scene_table:
            raise ConfigError(f"{source} [scene]: give name (a catalog scene) or path (a scene file), not both")
    scene = SceneConfig(
        name=_check_type(f"{source} [scene]", "name", scene_table.pop("name", "whitted"), str),
        path=_check_type(f"{source} [scene]", "path", scene_table.pop("path", ""), str),
        time=_check_type(f"{source} [scene]", "time", scene_table.pop("time", 0.0), float),
        params=tuple(sorted(scene_table.items())),
    )
    if scene.path and source not in ("<dict>", "<defaults>"):
        # A relative scene path is relative to the config file.
        candidate = Path(source).parent / scene.path
        if candidate.exists():
            scene = replace(scene, path=str(candidate))
    render = _dataclass_from(RenderConfig, data.get("render", {}), f"{source} [render]")
    base = Config()
    per_kind = {}
    for section in ("traversal", "frustum"):
        table = data.get(section, {})
        for key in table:
            if key not in RAY_KINDS:
                raise ConfigError(f"{source} [{section}]: unknown ray kind {key!r}; allowed: {', '.join(RAY_KINDS)}")
            _check_type(f"{source} [{section}]", key, table[key], str)
        current = getattr(base, section)
        per_kind[section] = PerKind(**{k: table.get(k, current.get(k)) for k in RAY_KINDS})
    materials = data.get("materials", {})
    if set(materials) - {"override"}:
        raise ConfigError(f"{source} [materials]: unknown key(s) {sorted(set(materials) - {'override'})}; allowed: override")
    plugins = data.get("plugins", {})
    if set(plugins) - {"load_entry_points"}:
        raise ConfigError(f"{source} [plugins]: unknown key(s) {sorted(set(plugins) - {'load_entry_points'})}; "
                          f"allowed: load_entry_points")
    for name, table in data.get("options", {}).items():
        if not isinstance(table, dict):
            raise ConfigError(f"{source} [options]: {name} must be a table [options.{name}] of that plugin's "
                              f"options, got {table!r}")
    options = tuple((name, tuple(sorted(table.items()))) for name, table in sorted(data.get("options", {}).items()))
    config = Config(scene=scene, render=render, traversal=per_kind["traversal"], frustum=per_kind["frustum"],
                    override=_check_type(f"{source} [materials]", "override", materials.get("override", "none"), str),
                    load_entry_points=_check_type(f"{source} [plugins]", "load_entry_points",
                                                  plugins.get("load_entry_points", False), bool),
                    options=options, source=source,
                    accel=_dataclass_from(AccelConfig, data.get("accel", {}), f"{source} [accel]"))
    try:
        return validate(config)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def read_toml(path: str, what: str) -> dict:
    """The table in TOML file ``path``; a missing or malformed file is a ConfigError naming it
    (``what``: "config", "matrix", ... for the message)."""
    file = Path(path)
    if not file.is_file():
        state = "is a folder, not a file" if file.is_dir() else \
            "is not a regular file" if file.exists() else "does not exist"
        raise ConfigError(f"{what} file {path!r} {state}")
    try:
        return tomllib.loads(file.read_bytes().decode("utf-8-sig"))  # a byte-order mark is only a mark
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}); TOML files must be UTF-8") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def load(path: str) -> Config:
    """Config from a TOML file; a missing or malformed file is a ConfigError naming it."""
    return from_dict(read_toml(path, "config"), source=str(path))


def with_overrides(config: Config, *, scene=None, traversal=(), frustum=(), packet=None, size=None,
                   depth=None, threads=None, scene_params=(), device=None) -> Config:
    """Apply command-line selectors. traversal/frustum: "NAME" (every kind) or "KIND=NAME"."""
    def apply(per_kind: PerKind, specs, what):
        values = {k: per_kind.get(k) for k in RAY_KINDS}
        for spec in specs:
            kind, equals, name = spec.rpartition("=")
            if equals and not kind:
                raise ConfigError(f"--{what} {spec!r}: no ray kind before '='; give KIND=NAME or NAME")
            if kind and kind not in RAY_KINDS:
                raise ConfigError(f"--{what} {spec!r}: unknown ray kind {kind!r}; allowed: {', '.join(RAY_KINDS)}")
            for k in ([kind] if kind else RAY_KINDS):
                values[k] = name
        return PerKind(**values)

    changes = {"traversal": apply(config.traversal, traversal, "traversal"),
               "frustum": apply(config.frustum, frustum, "frustum")}
    render = config.render
    if packet is not None:
        render = replace(render, packet=packet)
    if size is not None:
        render = replace(render, width=size[0], height=size[1])
    if depth is not None:
        render = replace(render, max_depth=depth)
    if threads is not None:
        render = replace(render, threads=threads)
    if device is not None:
        render = replace(render, device=device)
    scene_config = config.scene
    if scene is not None:
        is_file = Path(scene).suffix.lower() in (".obj", ".ply", ".stl", ".off", ".aff", ".glb", ".gltf")
        scene_config = SceneConfig(name="" if is_file else scene, path=scene if is_file else "",
                                   time=config.scene.time, params=() if scene != config.scene.name else config.scene.params)
    if scene_params:
        scene_config = replace(scene_config, params=tuple(sorted({**dict(scene_config.params), **dict(scene_params)}.items())))
    return validate(replace(config, render=render, scene=scene_config, **changes))


def parse_size(text: str, option: str = "--size") -> tuple[int, int]:
    """"WxH" -> (W, H); anything else is a ConfigError naming ``option``."""
    try:
        w, h = text.lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise ConfigError(f"{option} must look like 512x512, got {text!r}") from None

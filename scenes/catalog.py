"""Scene catalog: named scenes described by small TOML files, found on the search path.

Each ``scenes/catalog/<name>.toml`` says::

    name = "bunny"
    description = "Stanford Bunny, four levels of detail"
    loader = "mesh"                          # a key of LOADERS
    files = ["stanford-bunny/bun_zipper.ply"]  # relative to a folder of the search path
    animated = false
    [params]                                 # loader keyword arguments and their defaults;
    lod = 0                                  # a config's [scene] keys may override these
    [variants]                               # optional: a parameter that picks the file,
    lod = ["a.ply", "b.ply"]                 # files = variants[param][value] (value 0..n-1)
    [limits]                                 # every parameter's allowed values:
    lod = [0, 3]                             # [min, max] (a float bound allows floats),
    camera = ["auto", "static"]              # words, or words and a range: ["all", 0, 99]
    [camera]                                 # optional override: eye, look_at, up, fov
    [materials]                              # optional: override = "reflective"

Parameters are checked against ``[limits]`` before any loader runs (``check_params``), so a
parameter can neither crash a loader nor make it allocate without bound.

Loaders are functions ``load(files: list[Path], params: dict, time: float) -> Scene``
registered with ``@scene_loader("name")``; procedural generators are loaders with no files.
The scene search path is ``PACKETRT_SCENE_PATH`` (colon-separated folders).
"""
from __future__ import annotations

import errno
import os
import tomllib
from dataclasses import dataclass, field, replace
from importlib import import_module
from pathlib import Path

import numpy as np

from engine.core import checked
from engine.core.errors import ConfigError, ConfigTypeError, SceneError
from engine.core.scene import Camera, Scene, check_scene, checked_camera, override_materials

CATALOG_DIR = Path(__file__).with_name("catalog")
SCENE_PATH_VARIABLE = "PACKETRT_SCENE_PATH"

#: Modules whose import registers loaders.
LOADER_MODULES = ["scenes.meshfile", "scenes.whitted", "scenes.aff_animation", "scenes.spd_rings", "scenes.erw6",
                  "scenes.cosine", "scenes.bunny_floor"]

LOADERS: dict = {}
ANIMATORS: dict = {}


def scene_loader(name: str):
    """Register ``load(files, params, time) -> Scene`` under ``name``."""
    def decorate(function):
        LOADERS[name] = function
        return function
    return decorate


def scene_animator(name: str):
    """Register ``open(files, params) -> animation`` for loader ``name``: an object with
    ``start``, ``end`` (seconds), ``frames`` (the file's own count), ``animated`` and
    ``scene_at(time) -> Scene``, which parses once and places the scene per frame."""
    def decorate(function):
        ANIMATORS[name] = function
        return function
    return decorate


def _load_loader_modules() -> None:
    for module in LOADER_MODULES:
        import_module(module)


@dataclass
class SceneEntry:
    name: str
    description: str
    loader: str
    files: list
    params: dict
    animated: bool = False
    camera: dict = field(default_factory=dict)
    materials: dict = field(default_factory=dict)
    variants: dict = field(default_factory=dict)
    catalog_file: str = ""
    limits: dict = field(default_factory=dict)


def search_path() -> list[Path]:
    """Folders of PACKETRT_SCENE_PATH, in order (empty when unset)."""
    raw = os.environ.get(SCENE_PATH_VARIABLE, "")
    return [Path(p).expanduser() for p in raw.split(os.pathsep) if p.strip()]


def entries() -> dict:
    """{name: SceneEntry} for every catalog file."""
    found = {}
    for file in sorted(CATALOG_DIR.glob("*.toml")):
        try:
            data = tomllib.loads(file.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise SceneError(f"{file}: not valid TOML: {exc}") from None
        allowed = {"name", "description", "loader", "files", "params", "animated", "camera", "materials",
                   "variants", "limits"}
        unknown = set(data) - allowed
        if unknown:
            raise SceneError(f"{file}: unknown key(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
        entry = SceneEntry(data["name"], data.get("description", ""), data["loader"],
                           list(data.get("files", [])), dict(data.get("params", {})),
                           bool(data.get("animated", False)), dict(data.get("camera", {})),
                           dict(data.get("materials", {})), dict(data.get("variants", {})), str(file),
                           dict(data.get("limits", {})))
        unlimited = set(entry.params) - set(entry.limits)
        if unlimited:
            raise SceneError(f"{file}: parameter(s) {sorted(unlimited)} have no [limits] entry")
        found[entry.name] = entry
    return found


def check_param(scene: str, key: str, value, default, limit: list):
    """``value`` of parameter ``key`` of ``scene`` if ``limit`` allows it, else a ConfigError
    naming the scene, the key and what is allowed. ``limit``: allowed words and/or a [min, max]
    range; the range is of integers when both bounds and the default are integers."""
    where = f"scene {scene!r}: parameter {key}"
    words = [w for w in limit if isinstance(w, str)]
    bounds = [b for b in limit if not isinstance(b, str)]
    if isinstance(value, str) or not bounds:
        if value in words:
            return value
        integers = bool(bounds) and all(isinstance(b, int) for b in bounds) and isinstance(default, (int, str))
        kind = "an integer" if integers else "a number"
        allowed = " or ".join([repr(w) for w in words] + ([f"{kind} in {bounds[0]}..{bounds[1]}"] if bounds else []))
        wrong_type = not words if isinstance(value, str) else not bounds  # e.g. a word where a number belongs
        raise (ConfigTypeError if wrong_type else ConfigError)(f"{where} must be {allowed}, got {value!r}")
    lo, hi = bounds
    # A range of integers when its bounds are, and the default is an integer or one of the words
    # (the BART scenes' lights = "all" | 0..10000).
    integers = isinstance(lo, int) and isinstance(hi, int) and isinstance(default, (int, str))
    try:
        if integers:
            return checked.to_int(value, where, lo, hi)
        checked.to_float(value, where, lo, hi)
        return value
    except ConfigError as exc:
        if not words:
            raise
        kind = "an integer" if integers else "a number"
        raise type(exc)(f"{where} must be {' or '.join(map(repr, words))} or {kind} in {lo}..{hi}, "
                        f"got {value!r}") from None


def check_params(entry: SceneEntry, params: dict) -> dict:
    """The entry's defaults updated with ``params``, every one checked against ``[limits]``."""
    unknown = set(params) - set(entry.params)
    if unknown:
        raise ConfigError(f"scene {entry.name!r} has no parameter(s) {sorted(unknown)}; "
                          f"allowed: {sorted(entry.params) or 'none'}")
    merged = {**entry.params, **params}
    return {key: check_param(entry.name, key, value, entry.params[key], entry.limits[key])
            for key, value in merged.items()}


def find_files(entry: SceneEntry, params: dict | None = None) -> tuple[list[Path], list[str]]:
    """(resolved paths, missing relative names) for an entry's files on the search path.

    With ``[variants]``, the parameter's value picks the file (e.g. a bunny LOD).
    """
    params = {**entry.params, **(params or {})}
    names = list(entry.files)
    for param, choices in entry.variants.items():
        value = params.get(param)
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < len(choices):
            raise ConfigError(f"scene {entry.name!r}: {param} must be an integer in 0..{len(choices) - 1}, "
                              f"got {value!r}")
        names.append(choices[value])
    resolved, missing = [], []
    for relative in names:
        hit = next((folder / relative for folder in search_path() if (folder / relative).is_file()), None)
        if hit is None:
            missing.append(relative)
        else:
            resolved.append(hit)
    return resolved, missing


def missing_message(name: str, missing: list[str]) -> str:
    def named(folder: Path) -> str:  # a path entry that is no folder is likely the mistake
        return str(folder) if folder.is_dir() else f"{folder} ({'a file, not a folder' if folder.exists() else 'no such folder'})"

    folders = [named(p) for p in search_path()] or ["(nothing: PACKETRT_SCENE_PATH is not set)"]
    return (f"scene {name!r}: missing file(s) {', '.join(missing)}; looked in {', '.join(folders)}; "
            f"set {SCENE_PATH_VARIABLE} to the folder that holds them (e.g. ../shared/scenes)")


def _resolve(name: str, params: dict | None) -> tuple:
    """(entry, merged parameters, files) of catalog scene ``name``; unknown names, parameters
    and missing files raise."""
    _load_loader_modules()
    catalog = entries()
    if name not in catalog:
        raise ConfigError(f"unknown scene {name!r}; catalog scenes: {', '.join(sorted(catalog))} "
                          f"(or give [scene] path = \"file.obj\")")
    entry = catalog[name]
    merged = check_params(entry, dict(params or {}))
    files, missing = find_files(entry, merged)
    if missing:
        raise SceneError(missing_message(name, missing))
    if entry.loader not in LOADERS:
        raise SceneError(f"{entry.catalog_file}: loader {entry.loader!r} is not registered; "
                         f"known loaders: {', '.join(sorted(LOADERS))}")
    return entry, merged, files


def _as_entry(scene: Scene, entry: SceneEntry) -> Scene:
    """The loaded ``scene`` named and adjusted as its catalog entry says (camera, materials)."""
    scene = replace(scene, name=entry.name)
    if entry.camera:
        # The entry's camera is in the files' coordinates: move it with a re-centred scene.
        given = {k: (tuple(v) if isinstance(v, list) else v) for k, v in entry.camera.items()}
        camera = checked_camera(Camera(**{**scene.camera.__dict__, **given}), entry.catalog_file)
        origin = np.asarray(scene.origin, np.float64)
        if origin.any():
            camera = replace(camera, eye=tuple(camera.eye - origin), look_at=tuple(camera.look_at - origin))
        scene.camera = camera
        check_scene(scene)
    if entry.materials.get("override", "none") != "none":
        scene = override_materials(scene, entry.materials["override"])
    return scene


def load_named(name: str, params: dict | None = None, time: float = 0.0) -> Scene:
    """Load catalog scene ``name`` with ``params`` overriding the entry's defaults."""
    entry, merged, files = _resolve(name, params)
    return _as_entry(LOADERS[entry.loader](files, merged, time), entry)


def missing_file(file: Path) -> str:
    """Why ``file`` (not a regular file) cannot be read as a scene, for a message."""
    if file.is_dir():
        return "is a folder, not a file"
    try:
        file.stat()
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "is a loop of symbolic links"
        return "does not exist"
    return "is not a regular file"


def load_path(path: str, time: float = 0.0) -> Scene:
    """Load a scene file by its own path: .obj/.ply/.stl/.off through trimesh, .aff by the
    BART loader (when registered)."""
    _load_loader_modules()
    file = Path(path).expanduser()
    if not file.is_file():
        raise SceneError(f"scene file {path!r} {missing_file(file)}")
    suffix = file.suffix.lower()
    loader = "aff" if suffix == ".aff" else "mesh"
    if loader not in LOADERS:
        raise SceneError(f"{path}: no loader for {suffix!r} files is available")
    scene = LOADERS[loader]([file], {}, time)
    return scene


def describe(load: bool = True) -> list[dict]:
    """One row per catalog scene for ``packetrt scenes``: name, description, files found,
    animated (``packetrt animate`` renders it), and, when loadable, triangles, lights and
    moves_with_time (``render --time`` changes it)."""
    _load_loader_modules()
    rows = []
    for name, entry in sorted(entries().items()):
        files, missing = find_files(entry)
        row = {"name": name, "description": entry.description, "loader": entry.loader,
               "files_found": not missing, "missing": missing, "animated": entry.animated,
               "params": entry.params, "triangles": None, "lights": None}
        if load and not missing:
            try:
                scene = load_named(name)
                row["triangles"] = scene.n_triangles
                row["lights"] = len(scene.lights)
                # "animated": `packetrt animate` renders its path; a scene that only follows
                # `--time` (cosine-n: the kitchen around a static surface) is "moves_with_time".
                row["moves_with_time"] = entry.animated or scene.animated
            except (SceneError, ConfigError) as exc:
                row["error"] = str(exc)
        rows.append(row)
    return rows


def scene_from_config(scene_config, override: str = "none") -> Scene:
    """The Scene a config's [scene] section and [materials] override describe."""
    if scene_config.path:
        if scene_config.params:
            raise ConfigError(f"[scene] parameters {sorted(dict(scene_config.params))} apply to catalog "
                              f"scenes only, not to path = {scene_config.path!r}")
        scene = load_path(scene_config.path, scene_config.time)
    else:
        scene = load_named(scene_config.name, dict(scene_config.params), scene_config.time)
    return override_materials(scene, override)


class ScenePath:
    """A scene along its animation path: parsed once, then ``scene_at(time)`` per frame, equal
    to loading the scene at that time (``scene_from_config`` with ``time``).

    name: the scene's name; start, end: the path's range in seconds; frames: the scene's own
    frame count over it; animated: whether anything moves.
    """

    def __init__(self, name: str, animation, entry: SceneEntry | None, override: str):
        self.name, self.animation, self.entry, self.override = name, animation, entry, override
        self.start, self.end = float(animation.start), float(animation.end)
        self.frames, self.animated = int(animation.frames), bool(animation.animated)
        # (the path's materials, their overridden copies) of the last frame: the renderer keeps
        # its material table while the materials are the same objects, and fresh copies each
        # frame rebuilt it, textures too, inside the timed scene phase (Museum: 1.5 -> 15-47 ms).
        self._overridden = None

    def scene_at(self, time: float) -> Scene:
        scene = self.animation.scene_at(time)
        if self.entry is not None:
            scene = _as_entry(scene, self.entry)
        if self.override == "none":
            return scene
        if self._overridden is not None and len(self._overridden[0]) == len(scene.materials) \
                and all(a is b for a, b in zip(self._overridden[0], scene.materials)):
            return replace(scene, materials=self._overridden[1])
        overridden = override_materials(scene, self.override)
        self._overridden = (list(scene.materials), overridden.materials)
        return overridden


def open_path(scene_config, override: str = "none") -> ScenePath:
    """The animation path of a config's [scene] (a catalog scene, or a scene file by path).
    A scene whose loader cannot animate, or that does not move, raises ConfigError saying so."""
    _load_loader_modules()
    if scene_config.path:
        if scene_config.params:
            raise ConfigError(f"[scene] parameters {sorted(dict(scene_config.params))} apply to catalog "
                              f"scenes only, not to path = {scene_config.path!r}")
        file = Path(scene_config.path).expanduser()
        if not file.is_file():
            raise SceneError(f"scene file {scene_config.path!r} {missing_file(file)}")
        loader, files, params, entry, name = ("aff" if file.suffix.lower() == ".aff" else "mesh"), [file], {}, None, str(file)
    else:
        entry, params, files = _resolve(scene_config.name, dict(scene_config.params))
        loader, name = entry.loader, entry.name
    animated = sorted(e.name for e in entries().values() if e.animated)
    if loader not in ANIMATORS:
        raise ConfigError(f"scene {name!r} has no animation path to render (its loader {loader!r} cannot "
                          f"animate; `render --time T` renders one time of a scene that follows time; "
                          f"animated scenes: {', '.join(animated)})")
    path = ScenePath(name, ANIMATORS[loader](files, params), entry, override)
    if not path.animated:
        raise ConfigError(f"scene {name!r} does not move: nothing in it is animated "
                          f"(animated scenes: {', '.join(animated)})")
    return path

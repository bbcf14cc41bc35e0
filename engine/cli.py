"""The ``packetrt`` command line.

    packetrt render  [CONFIG] [selectors] [-o OUT.png] [--stats OUT.json] [--repeat N | --audit]
    packetrt audit   [CONFIG] [selectors] [--json OUT.json] [--report DIR] [--oracle embree|open3d|both]
                     [--scheduler [ADDRESS] [--workers N] [--tiles N]]
    packetrt animate [CONFIG] [selectors] -o DIR [--frames N | --fps F] [--start S] [--end E]
                     [--accel rebuild|refit|auto] [--stats OUT.json] [--resume] [--audit]
    packetrt bench   MATRIX.toml [--out DIR] [--repeat N] [--resume] [--device cpu|cuda]
                     [--scheduler [ADDRESS] [--workers N]] [--steady X [--retries N]]
    packetrt show    [CONFIG] [selectors] [--kind K] [--packet-index I] [-o OUT.png]
    packetrt view    [CONFIG] [selectors]
    packetrt plugins [--json]
    packetrt scenes  [--json]
    packetrt --version

selectors: --scene S  --param KEY=VALUE  --time T  --traversal KIND=NAME|NAME
           --frustum KIND=NAME|NAME  --packet N  --size WxH  --depth D  --threads T
           --device cpu|cuda  --override none|reflective|refractive  --strict

A user mistake -- a mistyped option included -- prints one line ``packetrt: error: ...`` and
exits with code 2; an audit that finds a mismatch exits with code 1. A texture or material
library a mesh names but that is missing is one ``packetrt: warning: ...`` line, and an error
under ``--strict``.
"""
from __future__ import annotations

import argparse
import difflib
import json
import math
import sys
import warnings
from pathlib import Path
from dataclasses import replace

from engine.core import atomic, checked
from engine.core.numba_settings import hide_setup_warnings
from engine.core.errors import ConfigError, PacketrtError, SceneError
from engine.render.report import frames_dict, stats_dict

EXIT_USAGE = 2
EXIT_MISMATCH = 1
#: The longest a test may keep ``packetrt view`` open (--exit-after): a day.
MAX_VIEW_SECONDS = 86400.0


class UsageError(Exception):
    """argparse's complaint about the command line, raised instead of printing the usage block."""


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose mistakes become ``UsageError`` (``main`` prints one line)."""

    def error(self, message):
        raise UsageError(message)


def _nearest_option(parser: argparse.ArgumentParser, argv: list, message: str) -> str:
    """``"; did you mean --size?"`` for the first unrecognised option of ``message``, matched
    against the options of the subcommand named in ``argv`` (else the top level's)."""
    if "unrecognized arguments:" not in message:
        return ""
    words = message.split("unrecognized arguments:", 1)[1].split()
    unknown = next((w.split("=", 1)[0] for w in words if w.startswith("-")), None)
    if unknown is None:
        return ""
    commands = parser.commands.choices  # set by build_parser
    chosen = commands.get(next((a for a in argv if a in commands), None), parser)
    options = [o for action in chosen._actions for o in action.option_strings]  # argparse has no public list
    match = difflib.get_close_matches(unknown, options, n=1, cutoff=0.6)
    return f"; did you mean {match[0]}?" if match else ""


def _scene_param(text: str):
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise ConfigError(f"--param must look like KEY=VALUE, got {text!r}")
    import tomllib

    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value  # a bare word is a string
    return key, parsed


def _add_selectors(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", nargs="?", help="TOML config (default: built-in defaults)")
    p.add_argument("--scene", help="catalog scene name or a mesh/.aff file path")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="scene parameter, e.g. lod=3 (repeatable)")
    p.add_argument("--time", type=_seconds, help="animation time for animated scenes")
    p.add_argument("--traversal", action="append", default=[], metavar="KIND=NAME|NAME")
    p.add_argument("--frustum", action="append", default=[], metavar="KIND=NAME|NAME")
    p.add_argument("--packet", type=int, help="packet side n (n x n rays): 2, 4, 8, 16 or 32")
    p.add_argument("--size", help="image size WxH")
    p.add_argument("--depth", type=int, help="max recursion depth")
    p.add_argument("--threads", type=int, help="threads (0 = all cores)")
    p.add_argument("--device", choices=["cpu", "cuda"],
                   help="where frames are rendered: cpu (numba on every core) or cuda (the GPU wavefront)")
    p.add_argument("--override", choices=["none", "reflective", "refractive"],
                   help="make every material reflective or refractive (Overbeck et al. Sec. 5)")
    p.add_argument("--strict", action="store_true",
                   help="a missing texture or material library is an error, not a warning")


def _seconds(text: str) -> float:
    """--time: a finite number of seconds (NaN would end up in the --stats JSON)."""
    from engine.render.config import MAX_TIME

    try:
        return checked.parse_float(text, "--time", -MAX_TIME, MAX_TIME)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--time ")) from None


def _cpu_only(config, command: str):
    """``config`` unchanged, or a ConfigError for a command that draws CPU packets or paths only."""
    if config.render.device != "cpu":
        raise ConfigError(f"packetrt {command}: device {config.render.device!r} is not supported here "
                          f"(it works on the CPU only; render, audit, animate and bench take --device cuda)")
    return config


def _config_from(args):
    from engine.render import config as cfg

    base = cfg.load(args.config) if args.config else cfg.Config()
    config = cfg.with_overrides(
        base, scene=args.scene, traversal=args.traversal, frustum=args.frustum, packet=args.packet,
        size=cfg.parse_size(args.size) if args.size else None, depth=args.depth, threads=args.threads,
        scene_params=[_scene_param(p) for p in args.param], device=getattr(args, "device", None))
    if args.time is not None:
        config = replace(config, scene=replace(config.scene, time=args.time))
    if args.override is not None:
        config = replace(config, override=args.override)
    return cfg.validate(config) if args.time is not None or args.override is not None else config


def _load_scene(config, strict: bool = False):
    """The config's scene; what its loader warns about (a missing texture) is one stderr line
    each, or with ``strict`` the error."""
    from scenes.catalog import scene_from_config

    with warnings.catch_warnings():
        # Overflow while a reader (trimesh, numpy) parses a file is checked afterwards and, if
        # it matters, reported as one error line; numpy's own warning lines would only add noise.
        warnings.simplefilter("ignore", RuntimeWarning)
        scene = scene_from_config(config.scene, config.override)
    for warning in scene.info.get("warnings", []):
        if strict:
            raise SceneError(f"{warning} (--strict)")
        print(f"packetrt: warning: {warning}", file=sys.stderr)
    return scene


def _distinct_outputs(*named) -> None:
    """(option, path or None) pairs: no two options name the same file, or the later write would
    replace the earlier output."""
    def resolved(path) -> Path:
        try:
            return Path(path).resolve()
        except (OSError, RuntimeError):  # a link loop: the output check names it next
            return Path(path).absolute()

    # Devices (/dev/null) take any number of writes: only files a write would replace count.
    given = [(option, resolved(path)) for option, path in named if path]
    given = [(option, path) for option, path in given if not atomic.is_device(path)]
    for i, (option, path) in enumerate(given):
        for other, other_path in given[:i]:
            if path == other_path:
                raise ConfigError(f"{other} and {option} both write {str(path)!r}: give each its own path")


def _png_output(option: str, path) -> None:
    """``path`` (an image output) ends in .png, or is a device such as /dev/null: the image is
    always a PNG, and x.jpg would hold PNG bytes under a JPEG name."""
    if path and Path(str(path)).suffix.lower() != ".png" and not atomic.is_device(path):
        raise ConfigError(f"{option} writes a PNG image; give a name ending in .png, got {str(path)!r}")


def _check_outputs(*named) -> None:
    """(option, path or None) pairs: each given file can be written and no two are the same,
    checked before the work."""
    for option, path in named:
        if path is not None and not str(path).strip():
            raise ConfigError(f"{option} needs a file name, got an empty one")
    _distinct_outputs(*named)
    for option, path in named:
        if path:
            atomic.output_file(path, option)


def _write_json(path: str, data: dict) -> None:
    atomic.write_json(path, data)


def cmd_render(args) -> int:
    from engine.gpu.choose import new_renderer
    from engine.render.image import save_png

    config = _config_from(args)
    _png_output("-o", args.output)
    _check_outputs(("-o", args.output), ("--stats", args.stats))
    if args.audit and args.repeat:
        raise ConfigError(f"--audit renders one frame with every ray checked against Embree (its times include the "
                          f"checking); --repeat {args.repeat} times frames: give one or the other")
    scene = _load_scene(config, args.strict)
    if args.audit:
        return _run_audit(scene, config, args.output, None, None, args.stats)
    renderer = new_renderer(scene, config)
    compile_seconds = renderer.warm_up()  # JIT compile or cache load, out of every frame time
    result = renderer.render()
    save_png(result.image, args.output)
    frames = [result.seconds["total"]] + [renderer.render().seconds["total"] for _ in range(args.repeat)]
    result.seconds["compile"] = compile_seconds
    if args.stats:
        renderer.with_counters(result)
    mrays = result.mrays_per_s()
    rates = ", ".join(f"{k} {result.rays[k]:,} rays {mrays[k]:.2f} Mrays/s" for k in result.rays if result.rays[k])
    timing = frames_dict(frames)
    over = f"median of {timing['n']} frames" if timing["n"] > 1 else "1 frame"
    print(f"{scene.name}: {scene.n_triangles:,} triangles, {config.render.width}x{config.render.height}, "
          f"{timing['median']:.2f} s/frame = {timing['fps']:.2f} FPS ({over}; compile {compile_seconds:.1f} s apart) "
          f"-> {args.output} (first frame: {rates})")
    if args.stats:
        _write_json(args.stats, stats_dict(scene, config, result, frames))
    return 0


def cmd_animate(args) -> int:
    from engine.animate.run import check_stats_target, run_animation
    from engine.render.config import validate

    if args.time is not None:
        raise ConfigError("animate renders the scene's path from --start to --end; --time (one moment) is for render")
    config = _config_from(args)
    if config.scene.time != 0:  # the path sets every frame's time; the config's was dropped unsaid
        raise ConfigError(f"[scene] time = {config.scene.time:g}: animate renders the scene's path from --start to "
                          f"--end; a config's time (one moment) is for render")
    if str(args.output).strip():
        check_stats_target(Path(args.output), args.stats)  # before _check_outputs makes its folder
    _check_outputs(("--stats", args.stats))
    if args.accel is not None:
        config = validate(replace(config, accel=replace(config.accel, update=args.accel)))
    return run_animation(config, args.output, frames=args.frames, fps=args.fps, start=args.start, end=args.end,
                         stats=args.stats, resume=args.resume, audit=args.audit)


def _repeat_count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of frames 0..1000, got {text!r}") from None
    if not 0 <= value <= 1000:
        raise argparse.ArgumentTypeError(f"expected a whole number of frames 0..1000, got {value}")
    return value


def cmd_show(args) -> int:
    from engine.debug.show import PICTURE_SIZE, write_show
    from engine.render.config import parse_size

    size = parse_size(args.picture, "--picture") if getattr(args, "picture", None) else PICTURE_SIZE
    if not (64 <= size[0] <= 4096 and 64 <= size[1] <= 4096):
        raise ConfigError(f"--picture must be between 64x64 and 4096x4096, got {size[0]}x{size[1]}")
    config = _cpu_only(_config_from(args), "show")
    _png_output("-o", args.output)
    _check_outputs(("-o", args.output))
    scene = _load_scene(config, args.strict)
    summary = write_show(scene, config, args.kind, args.packet_index, args.output, size)
    detail = ", ".join(f"{k} {v}" for k, v in summary.items() if k not in ("packet", "packets"))
    print(f"{args.kind} packet {summary['packet']} of {summary['packets']} ({detail}) -> {args.output}")
    return 0


def cmd_view(args) -> int:
    from engine.debug.view import VIEW_SIZE, display_problem, run_viewer
    from engine.render.config import validate

    exit_after = getattr(args, "exit_after", None)
    if exit_after is not None and not (math.isfinite(exit_after) and 0 <= exit_after <= MAX_VIEW_SECONDS):
        raise ConfigError(f"--exit-after must be a number of seconds in 0..{MAX_VIEW_SECONDS:g}, got {exit_after}")
    _check_outputs(("--status-file", getattr(args, "status_file", None)))
    # The command's own mistakes (a config, --device cuda) before what this machine lacks.
    config = _cpu_only(_config_from(args), "view")
    problem = display_problem()
    if problem:
        raise PacketrtError(problem)
    if args.size is None:
        config = validate(replace(config, render=replace(config.render, width=VIEW_SIZE[0], height=VIEW_SIZE[1])))
    run_viewer(_load_scene(config, args.strict), config, status_file=getattr(args, "status_file", None),
               exit_after=exit_after)
    return 0


def _run_audit(scene, config, image_path, json_path, report_dir, stats_path, oracle="embree", tiled=None) -> int:
    """Audit, write what was asked for and print the summary; ``tiled``: (report, image,
    mismatching pixels) of an audit already run over a Dask scheduler."""
    from validation.audit import audit

    from engine.render.image import save_png

    if tiled is None:
        report, result, bad_pixels = audit(scene, config, oracle=oracle)
        image = result.image
    else:
        (report, image, bad_pixels), result = tiled, None
    if image_path:
        save_png(image, image_path)
    if json_path:
        _write_json(json_path, report)
    if stats_path and result is not None:
        _write_json(stats_path, stats_dict(scene, config, result, audited=True))
    if report_dir:
        from validation.report import write_report

        write_report(report_dir, report, image, bad_pixels, config.render.width, config.render.height)
    def rows(by_kind, bad="mismatches", indent="  "):
        for kind, row in by_kind.items():
            if row["checked"]:
                print(f"{indent}{kind:<10} checked {row['checked']:>9,}  agree {row['agree']:>9,}  "
                      f"ties {row['ties']:>7,}  {bad} {row[bad]:>6,}")

    one_each = report.get("oracles", {"": report})
    against = " and ".join(f"{r['oracle']['name']} {r['oracle']['version']} (robust={r['oracle']['robust']})"
                           for r in one_each.values())
    print(f"audit {scene.name} ({scene.n_triangles:,} triangles) against {against}:")
    for name, sub in one_each.items():
        if name:
            print(f"  against {name}:")
        rows(sub["by_kind"], indent="    " if name else "  ")
        print(f"{'    ' if name else '  '}agreement {sub['agreement']:.6f}, max |dt| on agreeing hits "
              f"{sub['max_abs_t_err']:.3g}")
    between = report.get("oracle_disagreements")
    if between:
        print(f"  {' vs '.join(between['between'])} (the oracles with each other; does not fail the audit):")
        rows(between["by_kind"], bad="disagreements", indent="    ")
    return EXIT_MISMATCH if report["mismatch_count"] else 0


def cmd_audit(args) -> int:
    config = _config_from(args)
    if args.scheduler is None and (args.tiles is not None or args.workers is not None):
        raise ConfigError("--tiles and --workers split the audit over a --scheduler; give --scheduler too, "
                          "or leave them out")
    if args.scheduler is not None and args.oracle == "both":  # was refused inside the first Dask task
        raise ConfigError("--scheduler splits the audit into bands checked against one oracle; --oracle both "
                          "runs here only (or give --oracle embree or open3d)")
    if args.report is not None and not args.report.strip():
        raise ConfigError("--report needs a folder name, got an empty one")
    if args.report:
        from validation.report import REPORT_FILES

        _distinct_outputs(("--json", args.json), ("--report", args.report),
                          *(("--report", Path(args.report) / name) for name in REPORT_FILES))
    _check_outputs(("--json", args.json))
    if args.report:
        atomic.output_folder(args.report, "--report")
        _check_outputs(*(("--report", Path(args.report) / name) for name in REPORT_FILES))
    scene = _load_scene(config, args.strict)
    tiled = None
    if args.scheduler is not None:  # bands of rows as Dask tasks, merged into one report
        from engine.bench.cluster import audit_on_cluster

        workers = 1 if args.workers is None else args.workers  # 0 is a mistake, not the default
        tiles = min(2 * workers, config.render.height) if args.tiles is None else args.tiles
        tiled = audit_on_cluster(config, tiles, args.scheduler, workers, args.oracle)
    return _run_audit(scene, config, None, args.json, args.report, None, oracle=args.oracle, tiled=tiled)


def _delegate(module: str, function: str):
    """A subcommand whose code lives in its own module, imported only when that command runs."""
    def run(args) -> int:
        import importlib

        return getattr(importlib.import_module(module), function)(args)
    return run


def cmd_plugins(args) -> int:
    from engine.render.plugins import describe, load_entry_points

    loaded = load_entry_points()
    table = describe()
    table["entry_points_loaded"] = loaded
    if args.json:
        print(json.dumps(table, indent=2))
        return 0
    for group in ("traversals", "frusta"):
        print(f"{group}:")
        for row in table[group]:
            print(f"  {row['name']:<12} {row['doc']}")
    return 0


def cmd_scenes(args) -> int:
    from scenes.catalog import describe, search_path

    rows = describe(load=True)
    if args.json:
        print(json.dumps({"search_path": [str(p) for p in search_path()], "scenes": rows}, indent=2))
        return 0
    print(f"search path: {':'.join(str(p) for p in search_path()) or '(PACKETRT_SCENE_PATH not set)'}")
    print(f"{'name':<14} {'triangles':>10} {'lights':>6} {'animated':>8}  files")
    for r in rows:
        files = ("missing: " + ", ".join(r["missing"]) if not r["files_found"]
                 else f"found, but cannot be loaded: {r['error']}" if "error" in r else "found")
        tri = f"{r['triangles']:,}" if r["triangles"] is not None else "-"
        moving = "yes" if r["animated"] else "time" if r.get("moves_with_time") else "no"
        print(f"{r['name']:<14} {tri:>10} {r['lights'] if r['lights'] is not None else '-':>6} {moving:>8}  {files}")
    if any(r.get("moves_with_time") and not r["animated"] for r in rows):
        print("animated 'time': render --time moves it, but it has no animation path for packetrt animate")
    return 0


def _version() -> str:
    """The installed package's version (pyproject.toml), or "(not installed)" from a bare checkout."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("packetrt")
    except PackageNotFoundError:
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="packetrt", description="Embree-validated Whitted ray tracer "
                                     "with plugin traversals (large ray packets, ray-space hierarchy).")
    parser.add_argument("--version", action="version", version=f"packetrt {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    parser.commands = sub  # for the nearest-option hint of a mistyped option
    p = sub.add_parser("render", help="render an image")
    _add_selectors(p)
    p.add_argument("-o", "--output", default="out/render.png", help="PNG to write")
    p.add_argument("--stats", help="write timings, ray counts and counters as JSON")
    p.add_argument("--repeat", type=_repeat_count, default=0, metavar="N",
                   help="render N more frames in the same process after the first (FPS = median)")
    p.add_argument("--audit", action="store_true", help="also check every ray against Embree")
    p.set_defaults(run=cmd_render)
    p = sub.add_parser("audit", help="check every ray of a render against Embree")
    _add_selectors(p)
    p.add_argument("--json", help="write the audit report as JSON")
    p.add_argument("--report", help="write a report folder (JSON + mismatch image)")
    p.add_argument("--scheduler", nargs="?", const="local", metavar="ADDRESS",
                   help="split the audit into bands of rows run as Dask tasks: on the scheduler at ADDRESS, or "
                        "with no address on a local cluster started here")
    p.add_argument("--workers", type=int, help="worker processes of the local cluster (default 1)")
    p.add_argument("--tiles", type=int, help="bands of rows of a --scheduler audit (default: 2 per worker)")
    p.add_argument("--oracle", choices=["embree", "open3d", "both"], default="embree",
                   help="ground truth: Embree (default), Open3D's RaycastingScene, or both")
    p.set_defaults(run=cmd_audit)
    _add_animate_parser(sub)
    _add_bench_parser(sub)
    _add_show_parser(sub)
    _add_view_parser(sub)
    p = sub.add_parser("plugins", help="list traversal and frustum plugins")
    p.add_argument("--json", action="store_true")
    p.set_defaults(run=cmd_plugins)
    p = sub.add_parser("scenes", help="list catalog scenes")
    p.add_argument("--json", action="store_true")
    p.set_defaults(run=cmd_scenes)
    return parser


def _add_animate_parser(sub) -> None:
    p = sub.add_parser("animate", help="render a scene's animation path (BART) into a folder of frames")
    _add_selectors(p)
    p.add_argument("-o", "--output", default="out/animation", metavar="DIR",
                   help="folder for frame_NNNNN.png, preview, path.png and frames.json")
    p.add_argument("--frames", type=int, help="frame count over the range (default: the scene's own)")
    p.add_argument("--fps", type=float, help="frames per second of scene time, instead of --frames")
    p.add_argument("--start", type=float, help="first frame's time (default: the path's start)")
    p.add_argument("--end", type=float, help="last frame's time (default: the path's end)")
    p.add_argument("--accel", choices=["rebuild", "refit", "auto"],
                   help="how the BVH follows the motion (default: the config's [accel] update)")
    p.add_argument("--stats", help="write the path's frame statistics as JSON")
    p.add_argument("--resume", action="store_true", help="carry on an interrupted run in the same folder")
    p.add_argument("--audit", action="store_true", help="check every ray of every frame against Embree")
    p.set_defaults(run=cmd_animate)


def _add_bench_parser(sub) -> None:
    p = sub.add_parser("bench", help="run a benchmark matrix (Embree on the same rays in every cell)")
    p.add_argument("matrix", help="matrix TOML, e.g. benchmarks/smoke.toml")
    p.add_argument("--out", help="output folder (default: out/bench-<matrix name>)")
    p.add_argument("--repeat", type=int, help="timed repeats per cell (default: the matrix's, else 5)")
    p.add_argument("--resume", action="store_true", help="skip cells already in DIR/results.jsonl")
    p.add_argument("--device", choices=["cpu", "cuda"],
                   help="cuda: run a kind = \"gpu\" matrix on the GPU (default: the matrix's device)")
    p.add_argument("--scheduler", nargs="?", const="local", metavar="ADDRESS",
                   help="run the cells as Dask tasks: on the scheduler at ADDRESS (tcp://host:8786), or with "
                        "no address on a local cluster started here")
    p.add_argument("--workers", type=int, help="worker processes of the local cluster (default 1: one cell at a "
                                               "time, clean timings)")
    p.add_argument("--steady", type=float, metavar="X",
                   help="measure a cell again (up to --retries times) when the host ran more than X times slower "
                        "around it than at the run's fastest moment, and keep the steadiest measurement "
                        "(e.g. 1.1; default: measure once)")
    p.add_argument("--retries", type=int, help="most extra measurements of a cell under --steady (default 2)")
    p.set_defaults(run=_delegate("engine.bench.runner", "cmd_bench"))


def _add_show_parser(sub) -> None:
    p = sub.add_parser("show", help="debug picture of one packet: rays, frustum, visited BVH nodes (PNG)")
    _add_selectors(p)
    p.add_argument("--kind", default="primary", help="ray kind of the packet: primary, shadow, reflection, refraction")
    p.add_argument("--packet-index", type=int, default=None, help="which packet (default: one near the image centre)")
    p.add_argument("-o", "--output", default="out/show.png", help="PNG to write")
    p.add_argument("--picture", default="800x600", metavar="WxH", help="size of the PNG (default 800x600)")
    p.set_defaults(run=cmd_show)


def _add_view_parser(sub) -> None:
    p = sub.add_parser("view", help="interactive Open3D window with the live ray-traced image")
    _add_selectors(p)
    # For tests: the panel's labels and numbers as JSON after every frame; close after S seconds.
    p.add_argument("--status-file", help=argparse.SUPPRESS)
    p.add_argument("--exit-after", type=float, help=argparse.SUPPRESS)
    p.set_defaults(run=cmd_view)


def main(argv=None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = parser.parse_args(argv)
    except UsageError as exc:
        # One line instead of argparse's usage block; SystemExit(2) as argparse itself would.
        print(f"packetrt: error: {exc}{_nearest_option(parser, argv, str(exc))}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE) from None
    hide_setup_warnings()
    with atomic.undoing_made_folders() as undo:
        code = _run_command(args)
        if code not in (0, EXIT_MISMATCH):   # failed: no empty output folders left behind
            undo()
        return code


def _run_command(args) -> int:
    """The command's exit code; every expected failure is one line on stderr."""
    try:
        return args.run(args)
    except PacketrtError as exc:
        print(f"packetrt: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except MemoryError:
        print("packetrt: error: out of memory (the machine has less free memory than this render, scene "
              "or benchmark needs); render smaller or free memory", file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:  # a file that cannot be read: permissions, a folder given for a file ...
        print(f"packetrt: error: {exc.filename or ''}{': ' if exc.filename else ''}{exc.strerror or exc}",
              file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("packetrt: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

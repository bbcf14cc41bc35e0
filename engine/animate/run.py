"""``packetrt animate``: render a scene's animation path into a folder, resumably.

The folder gets, each written through a temporary file and a rename:

- ``frame_00000.png`` ... one PNG per frame (5 digits: at most ``MAX_FRAMES`` frames);
- ``frames.json``: the run's identity (config and frame times) and every finished frame's
  record, rewritten after each frame, so an interrupted run leaves whole frames and the
  records of exactly those; ``--resume`` renders only the frames missing from it;
- ``preview.webp`` (``preview.gif`` where Pillow has no WebP): the path as one animation;
- ``path.png``: frame time along the path, stacked by phase;
- and, with ``--stats FILE``, BART's numbers: ``{"path": {"frames": [...], "mean_fps",
  "slowest_seconds", "total_seconds", "phase_share", "policies"}, ...}``.
"""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np

from engine.animate.plot import plot_path
from engine.animate.preview import keep_for_preview, preview_format, shrink, write_preview
from engine.core.atomic import output_file, output_folder, remove_if_empty, write_json
from engine.core.errors import PacketrtError
from engine.gpu.choose import new_renderer
from engine.render.animation import AnimationRenderer, path_summary, plan_times
from engine.render.image import save_png, to_srgb8

FRAME_NAME = "frame_{:05d}.png"
RECORDS = "frames.json"
SCHEMA = 1


def _identity(config, times: list, audit: bool) -> dict:
    """What must match for ``--resume`` to carry on a run: the config (less the scene time,
    which the path sets), the frame times and whether frames are audited (a resumed --audit run
    took an earlier run's unaudited frames and called the path audited)."""
    settings = config.to_dict()
    settings["scene"].pop("time", None)
    return {"config": settings, "times": times, "audit": bool(audit)}


def _load_records(out: Path, identity: dict, resume: bool) -> dict:
    """{frame index: record} of an earlier run to carry on (``resume``), else {}; a folder that
    holds another run, or a run without ``resume``, is an error naming it. A frame whose image is
    gone or whose record is malformed is left out (rendered again)."""
    file = out / RECORDS
    if not file.exists():
        return {}
    if not resume:
        raise PacketrtError(f"{out} already holds an animation ({RECORDS}); give --resume to carry it on, "
                            f"or choose another folder")
    try:
        data = json.loads(file.read_text(encoding="utf-8"))
        frames = {int(k): v for k, v in data["frames"].items()}
        earlier = data["identity"]
    except OSError as exc:
        raise PacketrtError(f"{file}: cannot read ({exc.strerror or exc}); choose another folder") from None
    except (ValueError, KeyError, TypeError, AttributeError):
        raise PacketrtError(f"{file}: not a packetrt animation record (expected a JSON object with \"identity\" "
                            f"and \"frames\": {{index: record}}); choose another folder") from None
    if isinstance(earlier, dict):
        earlier.setdefault("audit", False)  # records written before the flag was kept: unaudited
    if earlier != json.loads(json.dumps(identity)):
        raise PacketrtError(f"{out} holds frames of a different animation (config, frame times or --audit "
                            f"differ); choose another folder")
    return {i: r for i, r in frames.items() if _well_formed(r) and _readable_image(out / FRAME_NAME.format(i))}


def _readable_image(path: Path) -> bool:
    """Whether an earlier frame's PNG is there and decodes whole (a run cut off mid-write, or a
    damaged file: the frame is rendered again rather than failing the preview at the end)."""
    from PIL import Image

    if not path.is_file():
        return False
    try:
        with Image.open(path) as picture:
            picture.load()
    except Exception:  # Pillow raises many types (OSError, SyntaxError, ValueError ...) for a bad file
        return False
    return True


def _well_formed(record) -> bool:
    """Whether an earlier frame's record has what the path summary reads (numeric seconds per
    phase, an accel policy); a frame whose record does not is rendered again."""
    if not isinstance(record, dict):
        return False
    seconds, accel = record.get("seconds"), record.get("accel")
    return (isinstance(seconds, dict) and isinstance(accel, dict) and isinstance(accel.get("policy"), str)
            and all(isinstance(seconds.get(phase), (int, float)) and not isinstance(seconds.get(phase), bool)
                    for phase in ("total", "scene", "accel", "trace", "shade")))


def _save_records(out: Path, identity: dict, records: dict) -> None:
    document = {"schema": SCHEMA, "identity": identity, "frames": {str(i): records[i] for i in sorted(records)}}
    write_json(out / RECORDS, document, "frame records")


def _frame_observer(audit: bool):
    """observer_for(scene, bvh) auditing every ray of a frame against an Embree scene built
    over that frame's triangles, or None."""
    if not audit:
        return None
    from validation.audit import AuditObserver, make_oracle

    def observer_for(scene, bvh):
        return AuditObserver(scene, bvh, [make_oracle("embree", scene.triangles)])
    return observer_for


def _against_fresh_tree(animator, frame, kept_observer, observer_for) -> dict:
    """A refitted frame rendered again over a fresh tree, both audited: {"differing_pixels": n,
    "ties": n of them where a ray of either render tied Embree, "unexplained": [pixels where
    the images differ with no tie]}. A refit bounds the same triangles, so only a tie (two
    valid answers) may change a pixel."""
    fresh = animator.render_with_fresh_tree(observer_for)
    width = frame.result.image.shape[1]
    differing = np.flatnonzero(np.any(frame.result.image.reshape(-1, 3) != fresh.image.reshape(-1, 3), axis=1))
    tied = kept_observer.tie_pixels | animator.fresh_observer.tie_pixels
    unexplained = [int(p) for p in differing if int(p) not in tied]
    return {"differing_pixels": int(differing.size), "ties": int(differing.size) - len(unexplained),
            "unexplained": [(p % width, p // width) for p in unexplained[:100]]}


def is_own_output(folder: Path, file) -> bool:
    """Whether ``file`` is one of the files an animation writes into ``folder`` (its frames,
    records, preview or path plot): ``--stats`` naming one replaced it with the JSON."""
    target = Path(file)
    if target.resolve().parent != folder.resolve():
        return False
    own = {RECORDS, "path.png", "preview.webp", "preview.gif"}
    return target.name in own or re.fullmatch(r"frame_\d{5}\.png", target.name) is not None


def check_stats_target(folder: Path, stats) -> None:
    """A PacketrtError when ``--stats`` names ``folder`` itself or one of the files written into
    it (the folder itself was refused only after the whole path had rendered, the stats lost)."""
    if stats and Path(stats).resolve() == folder.resolve():
        raise PacketrtError(f"--stats {stats} is the -o folder itself; give a file for the JSON "
                            f"(e.g. {folder / 'stats.json'})")
    if stats and is_own_output(folder, stats):
        raise PacketrtError(f"--stats {stats} is one of the files animate writes into {folder}/ (frames, "
                            f"{RECORDS}, preview, path.png); give another file")


def run_animation(config, out: str, *, frames=None, fps=None, start=None, end=None, stats=None,
                  resume: bool = False, audit: bool = False, progress=None) -> int:
    """Render the animation path of ``config``'s scene into folder ``out`` (see the module
    doc); returns the exit code (1 when an audited frame had a mismatch, or a refitted frame a
    pixel that differs from its fresh-tree render without a tie). A run that fails before its
    first frame removes the folder if it made it (and it is still empty)."""
    if not str(out).strip():
        raise PacketrtError("-o needs a folder name, got an empty one")
    folder = Path(out)
    check_stats_target(folder, stats)
    created = not folder.exists()
    try:
        return _run_animation(config, folder, frames, fps, start, end, stats, resume, audit, progress)
    except BaseException:
        if created:
            remove_if_empty(folder)
        raise


def _run_animation(config, folder: Path, frames, fps, start, end, stats, resume: bool, audit: bool,
                   progress) -> int:
    """``run_animation``'s work."""
    from scenes.catalog import open_path
    from tqdm import tqdm

    path = open_path(config.scene, config.override)
    times = plan_times(path, frames, fps, start, end)
    output_folder(folder, "output")
    for name in (RECORDS, f"preview.{preview_format()}", "path.png"):  # before the frames, not after
        output_file(folder / name, "output")
    identity = _identity(config, times, audit)
    records = _load_records(folder, identity, resume)
    todo = [i for i in range(len(times)) if i not in records]
    audit_observer = _frame_observer(audit)
    animator = AnimationRenderer(path, config, audit_observer, make_renderer=new_renderer)
    compile_seconds = animator.warm_up(times[todo[0]] if todo else times[0]) if todo else 0.0
    keep = keep_for_preview(len(times))
    pictures = {}
    audit_total = {"checked": 0, "mismatches": 0, "ties": 0, "unexplained": 0}
    bar = tqdm(total=len(times), initial=len(times) - len(todo), unit="frame", file=sys.stderr,
               disable=progress is False or (progress is None and not sys.stderr.isatty()), dynamic_ncols=True)
    previous = None
    for i in todo:
        if previous is not None and previous != i - 1:
            animator.restart()                 # frames were skipped: the next tree is built afresh
        frame = animator.frame(i, times[i])
        previous = i
        image8 = to_srgb8(frame.result.image)
        save_png(frame.result.image, str(folder / FRAME_NAME.format(i)))
        if audit:
            observer = animator.renderer.observer
            report = observer.report()
            ties = sum(row["ties"] for row in report["by_kind"].values())
            frame.record["audit"] = {"checked": report["rays_checked"], "mismatches": report["mismatch_count"],
                                     "ties": ties}
            if frame.record["accel"]["policy"] == "refit":
                frame.record["audit"]["against_fresh_tree"] = _against_fresh_tree(animator, frame, observer,
                                                                                   audit_observer)
        records[i] = frame.record
        _save_records(folder, identity, records)
        if i in keep:
            pictures[i] = shrink(image8)
        bar.set_postfix_str(f"t={times[i]:.2f}s {frame.record['seconds']['total'] * 1000:.0f} ms")
        bar.update(1)
    bar.close()
    for i in sorted(keep - set(pictures)):          # frames an earlier run rendered
        from PIL import Image

        with Image.open(folder / FRAME_NAME.format(i)) as picture:
            pictures[i] = shrink(np.asarray(picture.convert("RGB"), np.uint8))
    ordered = [records[i] for i in sorted(records)]
    if audit:  # every frame's, an earlier (audited) run's included
        for record in ordered:
            checked = record.get("audit", {})
            for key in ("checked", "mismatches", "ties"):
                audit_total[key] += int(checked.get(key, 0))
            compared = checked.get("against_fresh_tree")
            if compared:
                audit_total["unexplained"] += compared["differing_pixels"] - compared["ties"]
    summary = path_summary(ordered)
    span = times[-1] - times[0]
    # The preview plays in scene time: its kept frames spread over the path's span.
    write_preview([pictures[i] for i in sorted(pictures)], folder / f"preview.{preview_format()}",
                  span / (len(pictures) - 1) if len(pictures) > 1 and span > 0 else 0.1)
    plot_path(ordered, folder / "path.png", f"{path.name}, {config.render.width}x{config.render.height}, "
                                             f"accel {config.accel.update}")
    if stats:
        document = {
            "scene": path.name, "width": config.render.width, "height": config.render.height,
            "config": config.to_dict(), "frames_rendered": len(todo), "frames_resumed": len(times) - len(todo),
            "seconds": {"compile": compile_seconds, "parse": getattr(path.animation, "parse_seconds", None)},
            "path": summary,
        }
        if audit:
            document["audit"] = audit_total
        write_json(stats, document, "stats")
    share = summary["phase_share"]
    policies = summary["policies"]
    fps_text = f"{summary['mean_fps']:.2f}" if summary["mean_fps"] else "-"
    print(f"{path.name}: {len(times)} frames over {times[0]:g}..{times[-1]:g} s, {config.render.width}x"
          f"{config.render.height}, mean {fps_text} FPS, slowest {summary['slowest_seconds']:.3f} s; accel "
          f"{config.accel.update} ({', '.join(f'{n} {p}' for p, n in policies.items() if n)}) "
          f"{100 * share['accel']:.1f}% of the time, scene {100 * share['scene']:.1f}%; compile "
          f"{compile_seconds:.1f} s apart -> {folder}/")
    if audit:
        print(f"audit against Embree, every frame: {audit_total['checked']:,} rays checked, "
              f"{audit_total['ties']:,} ties, {audit_total['mismatches']:,} mismatches; refitted frames against "
              f"a fresh tree: {audit_total['unexplained']:,} differing pixels not explained by a tie")
        return 1 if audit_total["mismatches"] or audit_total["unexplained"] else 0
    return 0

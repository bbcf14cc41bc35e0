"""Fill ``.gpu-carry/`` with what packetrt's GPU benchmark needs on a lent GPU machine without network.

Run here (with network), from the repository root:

    PACKETRT_SCENE_PATH=../shared/scenes python tools/gpu_carry.py
    python tools/gpu_carry.py --scenes cornell-box --no-mitsuba     # a small carry

It writes, under ``--out`` (default ``.gpu-carry``, git-ignored):

- ``whl/``: CPython 3.12 manylinux wheels of numpy 2.4 (the device image's numpy 2.5 breaks
  numba-cuda's import: ``np.row_stack`` is gone), embreex and trimesh at this environment's
  versions (``pip download --no-deps``: the image has the rest);
- ``mitsuba.zip``: Mitsuba 3 and Dr.Jit trimmed by ``tools/gpu_wheels.py`` (the yardstick);
- ``scenes.zip``: the named folders of the scene search path, deflated (the kitchen's text
  ``.aff`` files pack 9.9 MB into about 3 MB).

and refuses (exit 2, one line) when the carry and the checkout's tracked files would pass the
64 MiB a device call may take. On the device, ``. tools/gpu_device_setup.sh`` installs it all;
then, e.g. ``python3 -m engine.cli bench benchmarks/gpu.toml --device cuda --out $OUT/g``.
One call that sets up and runs everything costs the machine's start (40-60 s) once.
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from engine.core.atomic import replacing  # noqa: E402  (after the path is set)
from engine.core.errors import PacketrtError  # noqa: E402

CALL_LIMIT = 64 * 2**20        # bytes one device call may carry, checkout included
DEFAULT_SCENES = ("bart-kitchen", "cornell-box", "stanford-bunny")
PYTHON = "3.12"                # the device image's CPython


def _gpu_wheels():
    spec = importlib.util.spec_from_file_location("packetrt_tool_gpu_wheels", ROOT / "tools" / "gpu_wheels.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def zip_scenes(search_path: Path, names, out: Path) -> int:
    """Deflate the folders ``names`` of ``search_path`` into ``out`` (paths relative to the
    search path, so the zip unpacks into a search path of its own); the files written."""
    files = 0
    missing = [n for n in names if not (search_path / n).is_dir()]
    if missing:
        raise PacketrtError(f"{search_path}: no scene folder(s) {', '.join(missing)}")
    with replacing(out) as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as target:
            for name in names:
                for path in sorted((search_path / name).rglob("*")):
                    if path.is_file():
                        target.write(path, path.relative_to(search_path).as_posix())
                        files += 1
    return files


def tracked_bytes(root: Path = ROOT) -> int:
    """Bytes of the checkout's tracked files (what travels with every device call)."""
    names = subprocess.run(["git", "ls-files", "-z"], cwd=root, capture_output=True, check=True).stdout
    return sum((root / n).stat().st_size for n in names.decode().split("\0") if n and (root / n).is_file())


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def check_size(carry: int, checkout: int, limit: int = CALL_LIMIT) -> None:
    """Refuse a carry that, with the checkout, would not fit one device call."""
    if carry + checkout > limit:
        raise PacketrtError(f"the carry ({carry / 2**20:.1f} MiB) and the checkout ({checkout / 2**20:.1f} MiB) "
                            f"pass the {limit / 2**20:.0f} MiB a device call may take: carry fewer scenes "
                            "(--scenes) or leave Mitsuba out (--no-mitsuba)")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=".gpu-carry", help="folder to fill (default .gpu-carry)")
    parser.add_argument("--scenes", nargs="*", default=list(DEFAULT_SCENES),
                        help=f"scene folders to carry (default {' '.join(DEFAULT_SCENES)})")
    parser.add_argument("--no-mitsuba", action="store_true", help="leave the Mitsuba yardstick out")
    args = parser.parse_args(argv)
    out = Path(args.out)
    try:
        search = os.environ.get("PACKETRT_SCENE_PATH", "").split(os.pathsep)[0]
        if args.scenes and not search:
            raise PacketrtError("PACKETRT_SCENE_PATH is not set: it names the folder the scenes are read from")
        search = Path(search) if args.scenes else None
        missing = [n for n in args.scenes if not (search / n).is_dir()]
        if missing:  # before any download
            raise PacketrtError(f"{search}: no scene folder(s) {', '.join(missing)}")
        wheels = _gpu_wheels()
        (out / "whl").mkdir(parents=True, exist_ok=True)
        for old in (out / "whl").glob("*.whl"):  # two versions of one package stop the install there
            old.unlink()
        from importlib.metadata import version
        for package in ("numpy==2.4.*", f"embreex=={version('embreex')}", f"trimesh=={version('trimesh')}"):
            print(f"  {wheels.download(package, PYTHON, out / 'whl').name}")
        if not args.no_mitsuba:
            if wheels.main(["--out", str(out / "mitsuba.zip"), "--python-version", PYTHON]) != 0:
                return 2
        if args.scenes:
            files = zip_scenes(search, args.scenes, out / "scenes.zip")
            print(f"  scenes.zip: {files} files of {', '.join(args.scenes)}")
        carry, checkout = folder_bytes(out), tracked_bytes()
        check_size(carry, checkout)
    except PacketrtError as exc:
        print(f"gpu_carry: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an unwritable --out, a full disk
        print(f"gpu_carry: {exc.filename or out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(f"{out}: {carry / 2**20:.1f} MiB (+ {checkout / 2**20:.1f} MiB of checkout) for carry=[\"{out}\"]")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Unpack the trimmed Mitsuba + Dr.Jit zip of ``tools/gpu_wheels.py`` on a machine without network.

    python tools/gpu_unpack.py .gpu-carry/mitsuba.zip /tmp/mitsuba-site
    PYTHONPATH=/tmp/mitsuba-site:$PWD python -c "import mitsuba; mitsuba.set_variant('cuda_ad_rgb')"

Standard library only (``zipfile``; the device has no ``unzip``). The folder is filled through a
temporary sibling and renamed into place when every file is out, so an interrupted unpack never
leaves a half package that imports; an existing folder is replaced. File modes stored in the zip
are restored. A zip built for another CPython (its ``packetrt-trim.json`` says which) is refused
with one line, since its extension modules could not load here. Exit status: 0 done, 2 refused.
"""
from __future__ import annotations

import json
import os
import shutil
import sys
import zipfile
from pathlib import Path

MANIFEST = "packetrt-trim.json"


def unpack(archive, folder) -> dict:
    """Extract ``archive`` into ``folder`` (replaced whole); the zip's manifest.

    Raises ValueError (one line) when the zip was built for another CPython or holds a path
    that would land outside ``folder``."""
    target = Path(folder).resolve()
    with zipfile.ZipFile(archive) as zipped:
        manifest = json.loads(zipped.read(MANIFEST)) if MANIFEST in zipped.namelist() else {}
        built_for = manifest.get("python")
        here = f"{sys.version_info.major}.{sys.version_info.minor}"
        if built_for and built_for != here:
            raise ValueError(f"{archive}: built for CPython {built_for}, this is {here}; "
                             f"rebuild with tools/gpu_wheels.py --python-version {here}")
        scratch = target.with_name(f".{target.name}.{os.getpid()}.unpacking")
        shutil.rmtree(scratch, ignore_errors=True)
        try:
            for info in zipped.infolist():
                path = (scratch / info.filename).resolve()
                if scratch.resolve() not in path.parents:
                    raise ValueError(f"{archive}: {info.filename!r} would land outside {folder}")
                zipped.extract(info, scratch)
                mode = (info.external_attr >> 16) & 0o777
                if mode and not info.is_dir():
                    os.chmod(path, mode)
            if target.exists():
                shutil.rmtree(target)
            os.replace(scratch, target)
        finally:
            shutil.rmtree(scratch, ignore_errors=True)
    return manifest


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: gpu_unpack.py ZIP FOLDER", file=sys.stderr)
        return 2
    try:
        manifest = unpack(args[0], args[1])
    except (ValueError, OSError, zipfile.BadZipFile) as exc:
        print(f"gpu_unpack: {exc}", file=sys.stderr)
        return 2
    print(f"{args[1]}: {', '.join(manifest.get('wheels', []))} "
          f"(variants {', '.join(manifest.get('variants', []))}); put it on PYTHONPATH")
    return 0


if __name__ == "__main__":
    sys.exit(main())

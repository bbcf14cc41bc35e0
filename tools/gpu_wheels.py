"""Pack Mitsuba 3 and Dr.Jit, trimmed, into one zip for a machine without network.

Run on a machine with network, from the repository root:

    python tools/gpu_wheels.py                      # -> .gpu-carry/mitsuba.zip (cp312, 3.9.1)
    python tools/gpu_wheels.py --python-version 3.11 --out /tmp/mitsuba-cp311.zip

It downloads the ``mitsuba`` wheel for CPython ``--python-version`` on manylinux x86_64 (no
dependencies resolved: ``pip download --no-deps --only-binary=:all:``), reads the ``drjit``
version that wheel requires from its METADATA, downloads that ``drjit`` wheel the same way, and
writes a zip of the two packages' files with everything a mesh-only scene does not need left
out (see ``kept``): the whole wheel is about 63 MB, more than the 64 MiB that may travel to the
device machine alongside the rest of a working tree.

Kept from mitsuba: the Python package files (``*.py``), every bundled shared library
(``lib*.so``: libmitsuba.so links all of them, libembree3.so included, even on the CUDA
variants), the core extension modules (``mitsuba_ext``, ``mitsuba_alias``), the variant
modules named by ``--variants`` (default ``cuda_ad_rgb`` and ``scalar_rgb``), the plugins in
``PLUGINS``; the dist-info's METADATA, WHEEL and licences. Dropped: the other variants, other
plugins, headers, CMake and pkg-config files, type stubs, the ``mitsuba`` executable, docs and
``data/`` -- the IOR and sun-sky tables and ``srgb.coeff`` (9 MB packed), which libmitsuba opens
only when an RGB value is upsampled to a spectrum: strace of a process building and querying a
mesh scene in scalar_rgb, llvm_ad_rgb and even llvm_ad_spectral opens no file under data/ and
no plugin but diffuse and uniform. Dr.Jit is kept whole (about 5 MB packed). Packed: about
24 MB.

The zip also holds ``packetrt-trim.json``: the versions, the CPython tag the wheels were built
for and the variants kept. ``tools/gpu_unpack.py`` (standard library only) extracts it on the
device and refuses a zip built for another Python.
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from engine.core.atomic import replacing  # noqa: E402  (after the path is set)
from engine.core.errors import PacketrtError  # noqa: E402

DEFAULT_OUT = ".gpu-carry/mitsuba.zip"
#: Plugins a mesh-only scene loads (diffuse + uniform: a mesh's default BSDF, checked by listing
#: the libraries a scalar_rgb / llvm_ad_rgb process maps after building and querying one), plus
#: what a minimal camera + film + sampler + path integrator scene would load, should one be needed.
PLUGINS = ("path", "perspective", "hdrfilm", "independent", "diffuse", "box", "gaussian", "uniform",
           "srgb", "d65")
DEFAULT_VARIANTS = ("cuda_ad_rgb", "scalar_rgb")
#: manylinux tags pip may accept (the wheels are manylinux_2_27 / _2_28).
PLATFORMS = ["manylinux2014_x86_64"] + [f"manylinux_2_{n}_x86_64" for n in range(17, 36)]
MANIFEST = "packetrt-trim.json"


def download(package: str, python_version: str, folder: Path) -> Path:
    """pip-download ``package`` ("name==version") as a binary wheel for CPython
    ``python_version`` on manylinux x86_64 into ``folder``; the wheel's path."""
    name = package.split("==")[0]
    command = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
               "--python-version", python_version, "--implementation", "cp", "-d", str(folder)]
    for platform in PLATFORMS:
        command += ["--platform", platform]
    result = subprocess.run(command + [package], capture_output=True, text=True)
    found = sorted(folder.glob(f"{name}-*.whl"))
    if result.returncode != 0 or not found:
        tail = (result.stderr or result.stdout).strip().splitlines()[-3:]
        raise PacketrtError(f"pip download {package} for cp{python_version.replace('.', '')} failed: "
                            + " | ".join(tail))
    return found[-1]


def required_drjit(mitsuba_wheel: Path) -> str:
    """The exact ``drjit`` requirement ("drjit==X.Y.Z") in the mitsuba wheel's METADATA."""
    with zipfile.ZipFile(mitsuba_wheel) as wheel:
        meta = next(n for n in wheel.namelist() if n.endswith(".dist-info/METADATA"))
        text = wheel.read(meta).decode("utf-8")
    match = re.search(r"^Requires-Dist:\s*drjit\s*==\s*([0-9][^\s;,]*)", text, re.MULTILINE)
    if not match:
        raise PacketrtError(f"{mitsuba_wheel.name}: no pinned drjit requirement in its METADATA")
    return f"drjit=={match.group(1)}"


def kept(name: str, variants, plugins=PLUGINS) -> bool:
    """Whether the wheel member ``name`` goes into the trimmed zip (see the module doc)."""
    parts = name.split("/")
    top = parts[0]
    if top.startswith("drjit"):  # drjit/ and drjit-X.dist-info/: whole
        return True
    if top.endswith(".dist-info"):
        return parts[-1] in ("METADATA", "WHEEL") or "licenses" in parts
    if top != "mitsuba" or name.endswith("/"):
        return False  # share/doc, folder entries
    rest = parts[1:]
    if len(rest) == 1:
        leaf = rest[0]
        if leaf.endswith(".py") or leaf == "py.typed":
            return True
        if leaf.startswith("lib") and ".so" in leaf:
            return True
        module = leaf.split(".")[0]
        if leaf.endswith(".so"):  # extension modules: the core two and the kept variants
            return module in ("mitsuba_ext", "mitsuba_alias") or module in variants
        return False
    if rest[0] == "python":
        return rest[-1].endswith(".py")
    if rest[0] == "plugins":
        return len(rest) == 2 and rest[1].endswith(".so") and rest[1][:-3] in plugins
    return False  # data/ (IOR and sun-sky tables, srgb.coeff), include/, cmake/, stubs


def pack(wheels, out: Path, variants, python_version: str) -> dict:
    """Write the trimmed zip of ``wheels`` to ``out`` (atomically); its manifest."""
    manifest = {"python": python_version, "variants": list(variants), "plugins": list(PLUGINS),
                "wheels": [w.name for w in wheels], "files": 0, "unpacked_bytes": 0}
    with replacing(out) as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as target:
            for wheel in wheels:
                with zipfile.ZipFile(wheel) as source:
                    for info in source.infolist():
                        if not kept(info.filename, variants):
                            continue
                        entry = zipfile.ZipInfo(info.filename, info.date_time)
                        entry.external_attr = info.external_attr
                        entry.compress_type = zipfile.ZIP_DEFLATED
                        target.writestr(entry, source.read(info), compresslevel=9)
                        manifest["files"] += 1
                        manifest["unpacked_bytes"] += info.file_size
            target.writestr(MANIFEST, json.dumps(manifest, indent=2) + "\n")
    return manifest


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mitsuba", default="3.9.1", help="mitsuba version (default 3.9.1)")
    parser.add_argument("--python-version", default="3.12", help="target CPython X.Y (default 3.12)")
    parser.add_argument("--variants", default=",".join(DEFAULT_VARIANTS),
                        help="comma-separated variant modules to keep (default cuda_ad_rgb,scalar_rgb)")
    parser.add_argument("--out", default=DEFAULT_OUT, help=f"zip to write (default {DEFAULT_OUT})")
    parser.add_argument("--wheels", help="folder already holding both wheels (skip the download)")
    args = parser.parse_args(argv)
    variants = tuple(v for v in args.variants.split(",") if v)
    try:
        with tempfile.TemporaryDirectory(prefix="gpu-wheels-") as scratch:
            if args.wheels:
                folder = Path(args.wheels)
                tag = "cp" + args.python_version.replace(".", "")
                wheels = [sorted(folder.glob(f"{n}-*-{tag}-*.whl")) for n in ("mitsuba", "drjit")]
                if not all(wheels):
                    raise PacketrtError(f"{folder}: no mitsuba and drjit wheels for {tag}")
                wheels = [w[-1] for w in wheels]
            else:
                folder = Path(scratch)
                mitsuba = download(f"mitsuba=={args.mitsuba}", args.python_version, folder)
                wheels = [mitsuba, download(required_drjit(mitsuba), args.python_version, folder)]
            manifest = pack(wheels, Path(args.out), variants, args.python_version)
    except PacketrtError as exc:
        print(f"gpu_wheels: {exc}", file=sys.stderr)
        return 2
    size = Path(args.out).stat().st_size
    print(f"{args.out}: {size / 1e6:.1f} MB packed, {manifest['files']} files, "
          f"{manifest['unpacked_bytes'] / 1e6:.1f} MB unpacked, from {', '.join(manifest['wheels'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Where numba keeps packetrt's compiled kernels, so that a stale cache is never served.

numba checks a cached function against its *own* source file only. A kernel compiled with a
callee from another module (every traversal inlines ``engine.core.triangle``) would keep the
old callee's machine code after that module changed, silently. So the cache folder is named
after a hash of every source file that defines compiled code: change any of them and the
kernels compile into (and load from) a fresh folder.

Nothing is written here: the hash only reads the sources, and numba creates the folder when it
first stores a kernel. The folder is ``$NUMBA_CACHE_DIR/packetrt-<hash>`` when the user set
``NUMBA_CACHE_DIR``, else ``$XDG_CACHE_HOME/packetrt/numba/<hash>`` (``~/.cache`` by default).
Folders of earlier source versions are left in place; ``make clean`` removes them.
"""
from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

#: Packages (and the tests, whose kernels call ours) whose compiled code depends on each other.
PACKAGES = ("engine", "traversals", "frusta", "validation", "scenes", "tests")
#: A file matters when it defines compiled code.
COMPILED = re.compile(rb"@(numba\.)?(njit|jit|intrinsic|vectorize|guvectorize|overload)\b")
ROOT = Path(__file__).resolve().parents[2]


def compiled_sources(root: Path = ROOT) -> list[Path]:
    """The .py files anywhere under ``root``'s packages that define numba-compiled code, sorted."""
    found = []
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            try:
                if COMPILED.search(path.read_bytes()):
                    found.append(path)
            except OSError:
                continue
    return found


def sources_hash(paths: list[Path], root: Path = ROOT) -> str:
    """sha1 over the relative path and bytes of every file in ``paths`` (hex, 40 characters)."""
    digest = hashlib.sha1()
    for path in paths:
        digest.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def cache_dir(root: Path = ROOT, environ=None) -> Path:
    """The numba cache folder for the current sources (see the module doc); not created here."""
    environ = os.environ if environ is None else environ
    version = sources_hash(compiled_sources(root), root)[:16]
    if environ.get("NUMBA_CACHE_DIR"):
        return Path(environ["NUMBA_CACHE_DIR"]) / f"packetrt-{version}"
    base = Path(environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "packetrt" / "numba" / version


def use_source_keyed_cache() -> Path:
    """Point numba's cache at ``cache_dir()``; must run before any kernel module is imported
    (numba picks a function's cache folder when it is decorated). Returns the folder."""
    import numba

    folder = cache_dir()
    numba.config.CACHE_DIR = str(folder)
    return folder

"""Keep numba's on-disk cache (``@njit(cache=True)``) from serving stale machine code.

numba checks a cached function against its *own* source file only. A kernel compiled with a
callee from another module (every traversal inlines ``engine.kernels``) keeps the old
callee's code after that module changes, silently. So: hash every source file that defines
compiled code; when the hash differs from the one stored beside the caches, delete all the
project's cache files once and store the new hash. Costs a few milliseconds per import.
"""
from __future__ import annotations

import hashlib
import re
from pathlib import Path

#: Packages (and the tests, whose kernels call ours) whose caches depend on each other.
PACKAGES = ("engine", "traversals", "frusta", "validation", "scenes", "tests")
#: A file matters when it defines compiled code.
COMPILED = re.compile(rb"@(numba\.)?(njit|jit|intrinsic|vectorize|guvectorize)\b")
STAMP_NAME = "packetrt-jit-sources.sha1"


def compiled_sources(root: Path) -> list[Path]:
    """The .py files under ``root``'s packages that define numba-compiled code, sorted."""
    found = []
    for package in PACKAGES:
        for path in sorted((root / package).glob("*.py")):
            try:
                if COMPILED.search(path.read_bytes()):
                    found.append(path)
            except OSError:
                continue
    return found


def sources_hash(paths: list[Path], root: Path) -> str:
    digest = hashlib.sha1()
    for path in paths:
        digest.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def invalidate_stale_caches(root: Path | None = None) -> int:
    """Delete the project's numba cache files if any compiled source changed; returns how many.

    Never raises: a read-only install simply keeps numba's own (per-file) checks.
    """
    root = Path(__file__).resolve().parent.parent if root is None else root
    try:
        current = sources_hash(compiled_sources(root), root)
        stamp = root / "engine" / "__pycache__" / STAMP_NAME
        if stamp.exists() and stamp.read_text().strip() == current:
            return 0
        removed = 0
        for package in PACKAGES:
            for cached in (root / package / "__pycache__").glob("*.nb[ic]"):
                cached.unlink(missing_ok=True)
                removed += 1
        stamp.parent.mkdir(exist_ok=True)
        stamp.write_text(current + "\n")
        return removed
    except OSError:
        return 0

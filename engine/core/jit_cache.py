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

Inside it, numba would file each module's kernels under a hash of the module's *absolute* folder,
so a second checkout of the same sources (a fresh clone, a moved or copied tree, a CI clone)
compiled everything again: about 4 minutes of CPU for the test suite, a minute for the first
render. ``CheckoutLocator`` files them under the module's path inside the checkout instead
(``engine/packet``, ``tests``) and stamps them with the file's content hash, so any checkout
whose compiled sources are byte for byte the same loads the kernels another one compiled.
"""
from __future__ import annotations

import functools
import hashlib
import os
import re
from pathlib import Path

from numba.core import caching

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


@functools.lru_cache(maxsize=None)
def _content_stamp(path: str, mtime_ns: int, size: int) -> str:
    """sha256 of a source file (hex); memoised per (path, mtime, size), so an edit is seen."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


class CheckoutLocator(caching._CacheLocator):
    """numba's cache locator for functions defined in this checkout's packages (see the module
    doc): the cache sub-folder is the module's folder relative to the checkout, the freshness
    stamp the file's content. Functions defined anywhere else get numba's own locators."""

    def __init__(self, py_func, py_file: str, relative_dir: str):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._cache_path = os.path.join(numba_cache_root(), relative_dir)

    def get_cache_path(self) -> str:
        return self._cache_path

    def get_source_stamp(self) -> str:
        st = os.stat(self._py_file)
        return _content_stamp(self._py_file, st.st_mtime_ns, st.st_size)

    def get_disambiguator(self) -> str:
        return str(self._lineno)   # as numba's: functions of one name in one file differ by line

    @classmethod
    def from_function(cls, py_func, py_file):
        if not numba_cache_root():
            return None
        try:
            relative = Path(py_file).resolve().relative_to(ROOT)
        except (ValueError, OSError):
            return None
        if relative.parts[0] not in PACKAGES:
            return None
        self = cls(py_func, py_file, relative.parent.as_posix())
        try:
            self.ensure_cache_path()
        except OSError:
            return None   # not writable: numba's next locator, as numba does
        return self


def numba_cache_root() -> str:
    import numba

    return numba.config.CACHE_DIR


def _cache_impl_classes() -> list:
    """numba's list of locator classes (``CacheImpl`` since 0.61, ``_CacheImpl`` before)."""
    impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl")
    return impl._locator_classes


def use_source_keyed_cache() -> Path:
    """Point numba's cache at ``cache_dir()`` and file this checkout's kernels by their path
    inside it (``CheckoutLocator``); must run before any kernel module is imported (numba picks a
    function's cache folder when it is decorated). Idempotent. Returns the folder."""
    import numba

    folder = cache_dir()
    numba.config.CACHE_DIR = str(folder)
    locators = _cache_impl_classes()
    if CheckoutLocator not in locators:
        locators.insert(0, CheckoutLocator)
    return folder

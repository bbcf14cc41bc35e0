"""The one output writer: every image, JSON, CSV, table and plot is written whole or not at all.

``replacing(target)`` hands out a temporary file beside the target; when the block ends the
temporary is flushed to disk and renamed over the target. A reader (or a crash, a full disk,
Ctrl-C) never sees half a file: on failure the temporary is removed and the old target, if any,
stays as it was. ``tests/test_hardening_outputs.py`` scans the sources: no other code opens an
output for writing except on a path ``replacing`` handed out. The one file that grows in place,
a benchmark's ``results.jsonl``, is appended to here too (``append_line``), one whole line at a
time.
"""
from __future__ import annotations

import contextvars
import json
import math
import os
import stat
from contextlib import contextmanager
from pathlib import Path

from engine.core.errors import PacketrtError


def _sync(path: Path) -> None:
    """Flush ``path``'s data to disk (so a rename never publishes an empty file after a crash)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _special_target(target: Path) -> bool:
    """Whether ``target`` (links already followed) is a character device (``/dev/null``), which
    is written straight into, as a rename would replace the device node by a file. A folder,
    FIFO, socket or block device is a PacketrtError: no file can be written whole there."""
    try:
        mode = target.stat().st_mode
    except FileNotFoundError:
        return False
    except OSError as exc:
        raise PacketrtError(f"cannot write {str(target)!r}: {exc.strerror or exc}") from None
    if stat.S_ISREG(mode):
        return False
    if stat.S_ISCHR(mode):
        return True
    what = "a folder" if stat.S_ISDIR(mode) else "a pipe" if stat.S_ISFIFO(mode) else \
        "a socket" if stat.S_ISSOCK(mode) else "a block device" if stat.S_ISBLK(mode) else "not a regular file"
    raise PacketrtError(f"cannot write {str(target)!r}: it is {what}, not a file")


def is_device(path) -> bool:
    """Whether ``path`` is a character device (``/dev/null``): written into, never replaced, so
    two outputs may name it. False for anything else, or a path that cannot be looked at."""
    try:
        return stat.S_ISCHR(Path(path).stat().st_mode)
    except OSError:
        return False


def _followed(path) -> Path:
    """``path`` with a symbolic link at its end followed: writing to a link writes the file it
    points to and leaves the link in place (a rename would replace the link itself)."""
    target = Path(path)
    return Path(os.path.realpath(target)) if target.is_symlink() else target


@contextmanager
def replacing(path) -> Path:
    """``with replacing(target) as tmp: write tmp`` -- then tmp is synced and renamed over
    ``target`` (folders created). The temporary name keeps the suffix, so format sniffing
    still works. A target that is a folder, pipe, socket or block device is an error, not a
    rename over it; a symbolic link is followed (its file is replaced, the link kept); a
    character device such as ``/dev/null`` is written straight into."""
    target = _followed(path)
    if _special_target(target):
        yield target
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.stem}.{os.getpid()}.tmp{target.suffix}")
    try:
        yield tmp
        _sync(tmp)
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through a temporary file and a rename."""
    with replacing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def plain_json(value):
    """``value`` with every non-finite float made ``None`` (strict JSON has no NaN or Infinity)
    and numpy scalars and arrays made Python numbers and lists."""
    if isinstance(value, dict):
        return {k: plain_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_json(v) for v in value]
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return plain_json(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def json_text(data) -> str:
    """Strict JSON text (NaN and infinities as null), indented, with a final newline."""
    return json.dumps(plain_json(data), indent=2, allow_nan=False) + "\n"


def write_json(path, data, what: str = "") -> None:
    """Write ``data`` as strict JSON; an OSError becomes one PacketrtError naming the path."""
    try:
        write_text(path, json_text(data))
    except OSError as exc:
        raise PacketrtError(f"cannot write {what + ' ' if what else ''}{str(path)!r}: "
                            f"{exc.strerror or exc}") from None


def append_line(path, line: str) -> None:
    """Append one whole ``line`` (it ends with a newline) to ``path``, flushed and synced. A
    write that fails part-way (a full disk, the file-size limit) is cut back off, so the file
    keeps whole lines only, and is one PacketrtError naming the file."""
    data = memoryview(line.encode("utf-8"))
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    try:
        size = os.lseek(fd, 0, os.SEEK_END)
        try:
            while data:  # unbuffered: nothing is left in a buffer to be written at close
                data = data[os.write(fd, data):]
            os.fsync(fd)
        except OSError as exc:
            try:
                os.ftruncate(fd, size)
            except OSError:
                pass  # then the reader skips the torn last line (``engine.bench.results``)
            raise PacketrtError(f"cannot append to {str(path)!r}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)


def truncate(path, size: int) -> None:
    """Cut ``path`` to its first ``size`` bytes (a torn last line of an appended record)."""
    with open(path, "r+b") as f:
        f.truncate(size)


def output_folder(path, what: str) -> Path:
    """``path`` as a folder to write outputs into, created if need be. A file in its place, or
    a folder that cannot be made or written, is one PacketrtError naming ``what`` (e.g.
    "--out") and the path."""
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise PacketrtError(f"{what} {str(folder)!r} is a file; give a folder")
    made = _made_folders.get()
    if made is not None:   # inside ``undoing_made_folders``: note each level this call makes
        missing = folder.absolute()
        while not missing.exists() and missing != missing.parent:
            made.append(missing)
            missing = missing.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PacketrtError(f"cannot make the {what} folder {str(folder)!r}: {exc.strerror or exc}") from None
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PacketrtError(f"{what} folder {str(folder)!r} is not writable")
    return folder


#: The folders output checks made inside ``undoing_made_folders`` (None outside one).
_made_folders: contextvars.ContextVar = contextvars.ContextVar("packetrt_made_folders", default=None)


@contextmanager
def undoing_made_folders():
    """A block (one command) whose output checks may make folders before the work: yields
    ``undo()``, which removes those of them that are still empty, deepest first -- for a command
    that failed, so that ``render -o new/x.png`` with a bad scene leaves no ``new/`` behind.
    Scoped to the block (a context variable), so nothing outlives the command."""
    made: list = []
    token = _made_folders.set(made)

    def undo() -> None:
        for folder in sorted(set(made), key=lambda p: len(p.parts), reverse=True):
            remove_if_empty(folder)

    try:
        yield undo
    finally:
        _made_folders.reset(token)


def remove_if_empty(folder: Path) -> None:
    """Remove ``folder`` when it holds nothing but empty files: what a command that made it and
    then failed before its first output leaves (an empty results file at most). Best effort:
    the error being raised is the one to report."""
    try:
        entries = list(Path(folder).iterdir())
        if all(e.is_file() and not e.is_symlink() and e.stat().st_size == 0 for e in entries):
            for e in entries:
                e.unlink()
            Path(folder).rmdir()
    except OSError:
        pass


def output_file(path, what: str) -> Path:
    """Checks, before any work, that the file ``path`` can be written later: not a folder, in a
    folder that exists or can be made, and is writable (the folder is made now). Otherwise one
    PacketrtError naming ``what`` (e.g. "--stats") and the path, so a long render never ends in
    an output it cannot write."""
    target = _followed(path)
    if target.is_dir():
        raise PacketrtError(f"{what} {str(path)!r} is a folder; give a file")
    try:
        if _special_target(target):  # /dev/null and the like: writable or not, no file to make
            if not os.access(target, os.W_OK):
                raise PacketrtError(f"cannot write {what} {str(path)!r}: permission denied")
            return Path(path)
    except PacketrtError as exc:
        raise PacketrtError(f"{what}: {exc}") from None
    folder = output_folder(target.parent, what)
    # A real file made and removed: permission bits do not tell for root, or on /proc and
    # read-only mounts.
    probe = folder / f".{target.stem}.{os.getpid()}.probe"
    try:
        probe.touch(exist_ok=False)
        probe.unlink()
    except OSError as exc:
        raise PacketrtError(f"cannot write {what} {str(target)!r}: {exc.strerror or exc}") from None
    return target


"""The one output writer (engine/core/atomic.py): outputs are written whole or not at all, and
no other code opens an output for writing -- checked by scanning every source file with ``ast``.
"""
from __future__ import annotations

import ast
import json
import os
import stat
from pathlib import Path

import pytest

from engine.core import atomic
from engine.core.errors import PacketrtError

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("engine", "scenes", "validation", "traversals", "frusta")
WRITER = "engine/core/atomic.py"
#: Calls that write a file: methods of paths, images, figures, arrays, frames; json.dump.
WRITING_METHODS = {"write_text", "write_bytes", "save", "savefig", "to_csv", "tofile", "imwrite", "dump"}
#: Files allowed their own writes, each with its reason. engine/debug/view.py belongs to
#: another owner: its hidden --status-file test hook writes a temporary and renames it itself.
KNOWN = {"engine/debug/view.py": "the viewer's --status-file test hook (temporary + os.replace)"}


def _replacing_names(tree: ast.AST) -> set:
    """Names bound by ``with replacing(...) as NAME`` (or ``atomic.replacing``) anywhere in the file."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.With, ast.AsyncWith)):
            for item in node.items:
                call = item.context_expr
                func = getattr(call, "func", None)
                called = getattr(func, "id", None) or getattr(func, "attr", None)
                if called == "replacing" and isinstance(item.optional_vars, ast.Name):
                    names.add(item.optional_vars.id)
    return names


def _opens_for_writing(call: ast.Call) -> bool:
    mode = call.args[1] if len(call.args) > 1 else next((k.value for k in call.keywords if k.arg == "mode"), None)
    return isinstance(mode, ast.Constant) and isinstance(mode.value, str) and any(c in mode.value for c in "wax+")


def writes_outside_the_writer(path: Path, relative: str) -> list:
    """["file:line: call"] of every write in ``path`` that does not go to a path ``replacing``
    handed out."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    handed_out = _replacing_names(tree)
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if isinstance(func, ast.Name) and func.id == "open":
            writing, name = _opens_for_writing(node), "open"
        elif isinstance(func, ast.Attribute) and func.attr in WRITING_METHODS \
                and not (isinstance(func.value, ast.Name) and func.value.id == "atomic"):  # the writer itself
            writing, name = True, func.attr
            if func.attr == "dump" and not (isinstance(func.value, ast.Name) and func.value.id in ("json", "pickle")):
                writing = False
        else:
            continue
        targets = [func.value] if isinstance(func, ast.Attribute) else []
        targets += list(node.args) + [k.value for k in node.keywords]
        if writing and not any(isinstance(t, ast.Name) and t.id in handed_out for t in targets):
            found.append(f"{relative}:{node.lineno}: {name}(...)")
    return found


def test_no_code_but_the_writer_opens_an_output():
    found = []
    for top in SOURCES:
        for path in sorted((ROOT / top).rglob("*.py")):
            relative = path.relative_to(ROOT).as_posix()
            if relative != WRITER and relative not in KNOWN:
                found += writes_outside_the_writer(path, relative)
    assert not found, "write through engine.core.atomic instead:\n" + "\n".join(found)


def test_the_scan_sees_a_planted_write(tmp_path):
    """The scan can fail: a plain write, an append and a savefig are caught; a write to the
    temporary of ``replacing`` is not."""
    planted = tmp_path / "bad.py"
    planted.write_text("def f(p, fig, img):\n    open(p, 'a').write('x')\n    fig.savefig(p)\n"
                       "    p.write_text('x')\n    with replacing(p) as tmp:\n        img.save(tmp)\n")
    assert sorted(line.split(": ")[1] for line in writes_outside_the_writer(planted, "bad.py")) == \
        ["open(...)", "savefig(...)", "write_text(...)"]


def test_a_failed_write_keeps_the_earlier_file(tmp_path):
    target = tmp_path / "out.json"
    target.write_text("earlier")
    with pytest.raises(RuntimeError):
        with atomic.replacing(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert target.read_text() == "earlier"
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]


def test_a_folder_in_the_way_is_one_error(tmp_path):
    with pytest.raises(PacketrtError, match="is a folder"):
        atomic.write_json(tmp_path, {"a": 1})


def test_write_json_is_strict_json(tmp_path):
    atomic.write_json(tmp_path / "x.json", {"nan": float("nan"), "t": (1, 2)})
    assert json.loads((tmp_path / "x.json").read_text()) == {"nan": None, "t": [1, 2]}


def test_a_pipe_at_an_output_path_is_one_error_before_any_write(tmp_path):
    fifo = tmp_path / "image.png"
    os.mkfifo(fifo)
    for check in (lambda: atomic.output_file(fifo, "-o"), lambda: atomic.write_text(fifo, "x")):
        with pytest.raises(PacketrtError, match="it is a pipe"):
            check()
    assert stat.S_ISFIFO(fifo.stat().st_mode)  # the node is left alone


def test_a_link_at_an_output_path_is_followed_and_kept(tmp_path):
    real = tmp_path / "real.json"
    real.write_text("earlier")
    link = tmp_path / "link.json"
    link.symlink_to(real)
    atomic.output_file(link, "--stats")
    atomic.write_json(link, {"a": 1})
    assert link.is_symlink() and json.loads(real.read_text()) == {"a": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.json", "real.json"]


def test_a_character_device_is_written_into_not_replaced(tmp_path):
    """``-o /dev/null`` discards the image; before, the rename replaced the device node by a
    regular file (as root). Tested on a device node of our own, where the system allows one."""
    node = tmp_path / "null"
    try:
        os.mknod(node, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    except (PermissionError, OSError):
        pytest.skip("cannot make a device node here (needs root)")
    atomic.output_file(node, "-o")
    atomic.write_text(node, "discarded")
    assert stat.S_ISCHR(node.stat().st_mode)
    assert [p.name for p in tmp_path.iterdir()] == ["null"]


def test_an_append_that_fails_part_way_leaves_whole_lines(tmp_path, monkeypatch):
    """A full disk (or the file-size limit) after part of a record: the part was left in
    results.jsonl, half a JSON line, and the error named no file."""
    import errno

    path = tmp_path / "results.jsonl"
    atomic.append_line(path, '{"cell":1}\n')
    real_write = os.write
    calls = []

    def full_after_four_bytes(fd, data):
        calls.append(len(data))
        if len(calls) == 1:
            return real_write(fd, bytes(data[:4]))
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "write", full_after_four_bytes)
    with pytest.raises(PacketrtError, match="results.jsonl.*No space left"):
        atomic.append_line(path, '{"cell":2,"seconds":[1.0,2.0]}\n')
    monkeypatch.undo()
    assert calls[0] > 4
    assert path.read_text() == '{"cell":1}\n'
    atomic.append_line(path, '{"cell":3}\n')
    assert path.read_text().splitlines() == ['{"cell":1}', '{"cell":3}']

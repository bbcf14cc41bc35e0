"""Outputs written whole or not at all: a temporary file beside the target, renamed over it.

A reader (or a crash, or Ctrl-C) never sees half an image, JSON, CSV or table; on failure the
temporary file is removed and the old target, if any, stays as it was.
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def replacing(path) -> Path:
    """``with replacing(target) as tmp: write tmp`` -- then tmp is renamed over ``target``
    (folders created). The temporary name keeps the suffix, so format sniffing still works."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.stem}.{os.getpid()}.tmp{target.suffix}")
    try:
        yield tmp
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through a temporary file and a rename."""
    with replacing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")

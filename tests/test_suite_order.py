"""The suite's own file order (``conftest.LONGEST_FIRST``): it names test files that exist, each
once, so a renamed or removed file cannot silently drop out of the longest-first start."""
from __future__ import annotations

from pathlib import Path

from conftest import LONGEST_FIRST


def test_longest_first_names_existing_test_files_once():
    here = Path(__file__).resolve().parent
    assert len(set(LONGEST_FIRST)) == len(LONGEST_FIRST)
    assert [name for name in LONGEST_FIRST if not (here / name).is_file()] == []

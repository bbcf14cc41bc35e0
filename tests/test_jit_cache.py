"""numba's cache is dropped when any compiled source changes, callees in other modules included."""
from __future__ import annotations

from engine.jit_cache import STAMP_NAME, invalidate_stale_caches


def make_project(root):
    for package in ("engine", "traversals"):
        (root / package / "__pycache__").mkdir(parents=True)
    (root / "engine" / "kernels.py").write_text("@njit(cache=True)\ndef f(x):\n    return x\n")
    (root / "engine" / "cli.py").write_text("def main():\n    pass\n")
    (root / "traversals" / "single.py").write_text("@njit(cache=True)\ndef g(x):\n    return f(x)\n")


def add_caches(root):
    for name in ("engine/__pycache__/kernels.f-1.py311.nbi", "engine/__pycache__/kernels.f-1.py311.1.nbc",
                 "traversals/__pycache__/single.g-1.py311.nbi"):
        (root / name).write_bytes(b"machine code")


def caches(root):
    return sorted(p.name for p in root.glob("*/__pycache__/*.nb[ic]"))


def test_caches_are_kept_while_sources_stay_the_same(tmp_path):
    make_project(tmp_path)
    invalidate_stale_caches(tmp_path)
    assert (tmp_path / "engine" / "__pycache__" / STAMP_NAME).exists()
    add_caches(tmp_path)
    assert invalidate_stale_caches(tmp_path) == 0
    assert len(caches(tmp_path)) == 3


def test_a_changed_callee_drops_every_cache(tmp_path):
    make_project(tmp_path)
    invalidate_stale_caches(tmp_path)
    add_caches(tmp_path)
    (tmp_path / "engine" / "kernels.py").write_text("@njit(cache=True)\ndef f(x):\n    return x + 1\n")
    assert invalidate_stale_caches(tmp_path) == 3
    assert caches(tmp_path) == []
    add_caches(tmp_path)
    assert invalidate_stale_caches(tmp_path) == 0


def test_files_without_compiled_code_do_not_count(tmp_path):
    make_project(tmp_path)
    invalidate_stale_caches(tmp_path)
    add_caches(tmp_path)
    (tmp_path / "engine" / "cli.py").write_text("def main():\n    return 1\n")
    assert invalidate_stale_caches(tmp_path) == 0
    assert len(caches(tmp_path)) == 3

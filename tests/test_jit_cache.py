"""numba's cache folder follows the compiled sources, callees in other modules and sub-packages
included, and importing engine writes nothing."""
from __future__ import annotations

import os
import subprocess
import sys

from engine.core.jit_cache import ROOT, cache_dir, compiled_sources


def make_project(root):
    (root / "engine" / "core").mkdir(parents=True)
    (root / "traversals").mkdir()
    (root / "engine" / "core" / "triangle.py").write_text("@njit(cache=True)\ndef f(x):\n    return x\n")
    (root / "engine" / "cli.py").write_text("def main():\n    pass\n")
    (root / "traversals" / "single.py").write_text("@njit(cache=True)\ndef g(x):\n    return f(x)\n")


def test_sources_are_found_in_sub_packages(tmp_path):
    make_project(tmp_path)
    found = [p.relative_to(tmp_path).as_posix() for p in compiled_sources(tmp_path)]
    assert found == ["engine/core/triangle.py", "traversals/single.py"]


def test_a_changed_callee_moves_the_cache(tmp_path):
    make_project(tmp_path)
    env = {"XDG_CACHE_HOME": str(tmp_path / "cache")}
    before = cache_dir(tmp_path, env)
    assert cache_dir(tmp_path, env) == before
    (tmp_path / "engine" / "core" / "triangle.py").write_text("@njit(cache=True)\ndef f(x):\n    return x + 1\n")
    after = cache_dir(tmp_path, env)
    assert after != before and after.parent == before.parent == tmp_path / "cache" / "packetrt" / "numba"


def test_files_without_compiled_code_do_not_count(tmp_path):
    make_project(tmp_path)
    env = {"XDG_CACHE_HOME": str(tmp_path / "cache")}
    before = cache_dir(tmp_path, env)
    (tmp_path / "engine" / "cli.py").write_text("def main():\n    return 1\n")
    assert cache_dir(tmp_path, env) == before


def test_numba_cache_dir_from_the_environment_is_honoured(tmp_path):
    make_project(tmp_path)
    folder = cache_dir(tmp_path, {"NUMBA_CACHE_DIR": str(tmp_path / "mine")})
    assert folder.parent == tmp_path / "mine" and folder.name.startswith("packetrt-")


def test_importing_engine_writes_nothing(tmp_path):
    """Import every package with the cache pointed at an empty folder and the repository's mtimes
    watched: no file appears or changes."""
    def snapshot():
        return {p: p.stat().st_mtime_ns for p in ROOT.rglob("*")
                if ".venv" not in p.parts and ".git" not in p.parts and "out" not in p.parts}

    before = snapshot()
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache"), "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("NUMBA_CACHE_DIR", None)
    run = subprocess.run([sys.executable, "-c", "import engine, engine.cli"], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert not (tmp_path / "cache").exists()
    assert snapshot() == before

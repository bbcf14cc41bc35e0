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
    # Left out: what the test runner itself writes while this test runs, from the other pytest
    # workers (hypothesis's example database and constants, pytest's cache). A clean clone's first
    # run failed here when another worker's hypothesis wrote .hypothesis/constants in between.
    # __pycache__: `make test` lets Python and pytest write byte code, which the other worker may
    # do at any moment (the child here is told not to).
    # A folder's own mtime is not watched, only that it exists: when another worker makes
    # engine/animate/__pycache__ the folder engine/animate changes its mtime (a clean clone's run
    # failed so in session 31); a file or folder that appears still shows as a new entry.
    runner_state = {".venv", ".git", "out", ".hypothesis", ".pytest_cache", "__pycache__"}

    def snapshot():
        return {p: (p.stat().st_mtime_ns if p.is_file() else None) for p in ROOT.rglob("*")
                if not runner_state.intersection(p.parts)}

    before = snapshot()
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache"), "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("NUMBA_CACHE_DIR", None)
    run = subprocess.run([sys.executable, "-c", "import engine, engine.cli"], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert not (tmp_path / "cache").exists()
    assert snapshot() == before


def copy_checkout(target):
    """The packages of this checkout (their .py files only) copied to ``target``."""
    import shutil

    from engine.core.jit_cache import PACKAGES

    for package in PACKAGES:
        shutil.copytree(ROOT / package, target / package, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return target


LOAD_ONE_KERNEL = """
import json, numpy as np, engine
from engine.query.order import spread_bits
spread_bits(np.uint64(5), 10, 3)
stats = spread_bits.stats
print(json.dumps({"hits": sum(stats.cache_hits.values()), "misses": sum(stats.cache_misses.values()),
                  "path": stats.cache_path, "module": engine.__file__}))
"""


def load_one_kernel(checkout, cache_home):
    import json

    env = {**os.environ, "XDG_CACHE_HOME": str(cache_home), "PYTHONPATH": str(checkout),
           "PYTHONDONTWRITEBYTECODE": "1"}
    env.pop("NUMBA_CACHE_DIR", None)
    run = subprocess.run([sys.executable, "-c", LOAD_ONE_KERNEL], env=env, cwd=checkout, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["module"].startswith(str(checkout))   # this checkout's engine, not the installed one
    return result


def test_a_second_checkout_of_the_same_sources_loads_the_first_ones_kernels(tmp_path):
    """Two copies of the checkout in different folders share one cache: the second compiles
    nothing. A copy whose compiled sources differ uses a folder of its own and compiles."""
    first, second, changed = (copy_checkout(tmp_path / name) for name in ("a", "b", "c"))
    with open(changed / "engine" / "query" / "order.py", "a") as source:
        source.write("\n\n@njit(cache=True)\ndef _another_kernel(x):\n    return x\n")
    cache = tmp_path / "cache"
    compiled = load_one_kernel(first, cache)
    assert (compiled["hits"], compiled["misses"]) == (0, 1)
    assert compiled["path"].endswith(os.path.join("engine", "query"))   # the module's path in the checkout
    loaded = load_one_kernel(second, cache)
    assert (loaded["hits"], loaded["misses"]) == (1, 0) and loaded["path"] == compiled["path"]
    other = load_one_kernel(changed, cache)
    assert (other["hits"], other["misses"]) == (0, 1) and other["path"] != compiled["path"]

"""The machine a benchmark ran on: CPU, cores, threads, library versions, the git commit."""
from __future__ import annotations

import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "absent"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _git() -> dict:
    def run(*args):
        try:
            return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""
    commit = run("rev-parse", "HEAD") or "unknown"
    return {"commit": commit, "dirty": bool(run("status", "--porcelain", "--untracked-files=no"))}


def machine_info() -> dict:
    """CPU, cores, numba threads, library versions and the project's git commit."""
    import numba

    from engine.core.embree_scene import library_version

    try:
        embree_version = library_version()
    except Exception:  # no usable Embree: the cells that need it will say so
        embree_version = "unavailable"
    return {"cpu": _cpu_model(), "cores": os.cpu_count(), "numba_threads": numba.config.NUMBA_NUM_THREADS,
            "threading_layer": numba.config.THREADING_LAYER, "platform": platform.platform(),
            "python": platform.python_version(), "numpy": np.__version__, "numba": numba.__version__,
            "embreex": _version("embreex"), "embree": embree_version, "open3d": _version("open3d"),
            "packetrt": _version("packetrt"), "git": _git()}

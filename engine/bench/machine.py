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


def _cpuinfo_fields() -> dict:
    """The first processor's fields of /proc/cpuinfo ({} where there is none)."""
    fields = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if not line.strip():
                break
            key, _, value = line.partition(":")
            fields[key.strip()] = value.strip()
    except OSError:
        pass
    return fields


def cpu_identity() -> dict:
    """What tells two hosts with the same model name apart (a virtual machine may report only
    "AMD EPYC" for a Zen 3 and a Zen 5): LLVM's name for the host CPU, which is what numba
    compiles for (``znver5``), the vendor's family / model / stepping, and the widest float
    vectors the kernels may use (``avx512``, ``avx2``, ...). Sessions 28-34 ran on 2-core
    "AMD EPYC" hosts that differed in all three, and their timings differ by 2x."""
    import llvmlite.binding as llvm

    fields = _cpuinfo_fields()
    flags = set(fields.get("flags", "").split())
    features = set(llvm.get_host_cpu_features().flatten().split(","))
    vector = next((name for name, flag in (("avx512", "avx512f"), ("avx2", "avx2"), ("avx", "avx"),
                                          ("sse4.2", "sse4_2"))
                   if flag in flags or f"+{flag.replace('_', '.')}" in features), "other")
    return {"llvm_cpu": llvm.get_host_cpu_name(), "family": fields.get("cpu family", "?"),
            "model": fields.get("model", "?"), "stepping": fields.get("stepping", "?"), "vector": vector}


def cpu_label(machine: dict) -> str:
    """'AMD EPYC (znver5, avx512)' from a machine record; records written before the identity
    was kept give the model name alone."""
    identity = machine.get("cpu_identity")
    if not identity:
        return machine["cpu"]
    return f"{machine['cpu']} ({identity['llvm_cpu']}, {identity['vector']})"


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
    return {"cpu": _cpu_model(), "cpu_identity": cpu_identity(), "cores": os.cpu_count(), "numba_threads": numba.config.NUMBA_NUM_THREADS,
            "threading_layer": numba.config.THREADING_LAYER, "platform": platform.platform(),
            "python": platform.python_version(), "numpy": np.__version__, "numba": numba.__version__,
            "embreex": _version("embreex"), "embree": embree_version, "open3d": _version("open3d"),
            "packetrt": _version("packetrt"), "git": _git()}

"""The machine record tells hosts with the same model name apart (engine.bench.machine)."""
import llvmlite.binding as llvm

from engine.bench.figures import machine_line
from engine.bench.machine import cpu_identity, cpu_label, machine_info


def test_identity_names_the_cpu_numba_compiles_for_and_its_vector_width():
    identity = cpu_identity()
    assert identity["llvm_cpu"] == llvm.get_host_cpu_name()
    assert identity["vector"] in ("avx512", "avx2", "avx", "sse4.2", "other")
    flags = open("/proc/cpuinfo").read()
    if " avx512f" in flags:
        assert identity["vector"] == "avx512"
    elif " avx2" in flags:
        assert identity["vector"] == "avx2"


def test_summary_line_carries_the_identity_and_reads_older_records():
    machine = machine_info()
    record = {"machine": machine, "threads": 2}
    line = machine_line([record])
    assert f"({machine['cpu_identity']['llvm_cpu']}, {machine['cpu_identity']['vector']})" in line
    older = {k: v for k, v in machine.items() if k != "cpu_identity"}
    assert cpu_label(older) == machine["cpu"]
    assert machine_line([{"machine": older, "threads": 2}]).startswith(f"{machine['cpu']}, 2 threads")

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


def test_summary_line_names_every_machine_of_mixed_records():
    """Records from a cluster's workers or a --resume on another host were all summarised under
    the first record's machine ("2 threads" over rows measured with 1)."""
    machine = machine_info()
    other = dict(machine, cpu="Other CPU", cpu_identity=dict(machine["cpu_identity"], llvm_cpu="other"))
    records = [{"machine": machine, "threads": 2}, {"machine": machine, "threads": 1},
               {"machine": machine, "threads": 1}, {"machine": other, "threads": 1}]
    line = machine_line(records)
    assert line.startswith("mixed machines: ")
    assert f"{cpu_label(machine)}, 2 threads (1 row); {cpu_label(machine)}, 1 threads (2 rows); " \
           f"{cpu_label(other)}, 1 threads (1 row)" in line
    assert machine_line(records[:1]).startswith(f"{cpu_label(machine)}, 2 threads;")

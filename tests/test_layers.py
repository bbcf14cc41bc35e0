"""The architecture's layers, checked by walking every import with ``ast``.

Each package has a rank; a module may import only from its own package or from packages of a
lower rank (lazy imports inside functions count too: they are dependencies all the same):

    0  engine.core                                  data contracts, BVH, triangle test, registry
    1  engine.packet, engine.rayspace               the two papers' support code
    1.5 engine.query                                mesh queries: the 8-wide tree and its per-ray walk,
                                                    and the packet walk for coherent rays
    2  traversals, frusta, scenes                   plugins and scene loaders
    3  engine.render                                tracer, Whitted loop, plugin composition
    3.5 engine.gpu                                  the CUDA device: its frame reuses render's lane math
    4  validation                                   audits against the oracles
    5  engine.bench, engine.debug, engine.animate   benchmark runner, debug pictures, animation paths
    6  engine (its __init__), engine.api, engine.cli  the public faces

Two packages of one rank do not import each other, no module imports a ``_private`` name from
another package, and the module graph has no cycle.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCE_PACKAGES = ("engine", "traversals", "frusta", "scenes", "validation")
RANKS = {
    "engine.core": 0, "engine.packet": 1, "engine.rayspace": 1, "traversals": 2, "frusta": 2, "scenes": 2,
    # trimesh's interface: the 8-wide tree and its per-ray walk (also the ``wide`` traversal's), and
    # the packet walk for coherent rays
    "engine.query": 1.5,
    "engine.render": 3, "engine.gpu": 3.5, "validation": 4, "engine.bench": 5, "engine.debug": 5, "engine.animate": 5,
    "engine": 6,  # engine/__init__.py, engine/api.py, engine/cli.py: one layer of public faces
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def package_of(module: str) -> str:
    """The ranked package a module belongs to (longest prefix in RANKS)."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        name = ".".join(parts[:n])
        if name in RANKS:
            return name
    raise AssertionError(f"module {module} is in no ranked package; add its package to RANKS")


def project_modules() -> dict:
    """{module name: path} of every project source file."""
    found = {}
    for top in SOURCE_PACKAGES:
        for path in sorted((ROOT / top).rglob("*.py")):
            found[module_name(path)] = path
    return found


def imports_of(module: str, path: Path, known: dict) -> list:
    """[(imported project module, [names imported from it], line)] of every import in the file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in SOURCE_PACKAGES:
                    out.append((alias.name, [], node.lineno))
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = module.split(".") if is_package else module.split(".")[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            if base.split(".")[0] not in SOURCE_PACKAGES:
                continue
            names = [a.name for a in node.names]
            submodules = [f"{base}.{n}" for n in names if f"{base}.{n}" in known]
            if submodules:
                out.extend((m, [], node.lineno) for m in submodules)
            else:
                out.append((base, names, node.lineno))
    return out


MODULES = project_modules()
EDGES = {m: imports_of(m, p, MODULES) for m, p in MODULES.items()}


def test_every_module_has_a_ranked_package():
    for module in MODULES:
        package_of(module)


def test_no_import_points_up_a_layer_or_across_one():
    wrong = []
    for module, edges in EDGES.items():
        mine = package_of(module)
        for target, _, line in edges:
            theirs = package_of(target)
            if theirs == mine:
                continue
            if RANKS[theirs] > RANKS[mine]:
                wrong.append(f"{MODULES[module].relative_to(ROOT)}:{line}: {mine} (rank {RANKS[mine]}) imports "
                             f"{target} (rank {RANKS[theirs]}): up a layer")
            elif RANKS[theirs] == RANKS[mine]:
                wrong.append(f"{MODULES[module].relative_to(ROOT)}:{line}: {mine} imports {target} of the same "
                             f"rank {RANKS[mine]}")
    assert not wrong, "\n".join(wrong)


def test_no_private_names_cross_a_package():
    wrong = []
    for module, edges in EDGES.items():
        for target, names, line in edges:
            private = [n for n in names if n.startswith("_")]
            if private and package_of(target) != package_of(module):
                wrong.append(f"{MODULES[module].relative_to(ROOT)}:{line}: imports {private} from {target}")
    assert not wrong, "\n".join(wrong)


def test_plugins_import_only_the_engine_core_and_its_packet_rayspace_and_query_support():
    allowed = {"engine.core", "engine.packet", "engine.rayspace", "engine.query", "traversals", "frusta"}
    wrong = [f"{MODULES[m].relative_to(ROOT)}:{line}: {target}"
             for m, edges in EDGES.items() if package_of(m) in ("traversals", "frusta")
             for target, _, line in edges if package_of(target) not in allowed]
    assert not wrong, "\n".join(wrong)


def test_no_import_cycle():
    graph = {m: {t if t in MODULES else t.rsplit(".", 1)[0] for t, _, _ in edges} & set(MODULES)
             for m, edges in EDGES.items()}
    # A package's __init__ is imported with each of its modules: not an edge back.
    for module in graph:
        graph[module] -= {p for p in graph[module] if module.startswith(p + ".")}
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                cycle = stack[stack.index(nxt):] + [nxt]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = "done"

    for module in sorted(graph):
        if module not in state:
            visit(module)


def test_the_walker_sees_a_planted_violation(tmp_path):
    """The checks can fail: a core module importing the CLI is caught as an upward import."""
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from engine.cli import main\n")
    (target, names, line), = imports_of("engine.core.bad", bad, MODULES)
    assert (target, names, line) == ("engine.cli", ["main"], 2)
    assert RANKS[package_of(target)] > RANKS[package_of("engine.core.bad")]

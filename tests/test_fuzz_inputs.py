"""Property-based hardening (issue 16): malformed and extreme OBJ, MTL, PLY, .aff and TOML
inputs and absurd numbers, run through the CLI's ``main()`` in this process; and odd values for
every argument of ``RayTracer`` and ``RayMeshIntersector`` and their query keywords (session 37),
which must be answered or refused as one-line packetrt errors.

Whatever the input, the promise is: exit code 0 or 2; for 2, exactly one stderr line
``packetrt: error: ...``; never a traceback; the output path holds either the earlier file,
untouched, or a whole new PNG -- never half of one, and no temporary left beside it. Memory
stays bounded because every size a user can name (scene parameters, image size) is checked
against a range before any work.

Profiles (``HYPOTHESIS_PROFILE``): ``ci`` (the default: derandomized, a few examples per
property, well under a minute in all) and ``long`` (randomized, hundreds of examples each,
for a local hunt).
"""
from __future__ import annotations

import io
import os
import resource
import warnings
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from engine.cli import main

settings.register_profile("ci", max_examples=50, derandomize=True, deadline=None, database=None,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
settings.register_profile("long", max_examples=400, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

PEAK_KIB = 4 * 2**20  # 4 GiB
EARLIER = b"an earlier render that must survive a failed run"
SMALL = ["--size", "8x8", "--depth", "1"]

# -- numbers a user might type, absurd ones first ------------------------------------------------
WEIRD_WORDS = ["nan", "-nan", "inf", "-inf", "1e39", "-1e39", "1e16", "1e14", "3.4e38", "1e-45", "-0",
               "0x10", "1_0", "", "abc", "1e", "--1", "9" * 40, "0", "1", "-1", "2", "0.5"]
numbers = st.one_of(st.sampled_from(WEIRD_WORDS),
                    st.floats(allow_nan=True, allow_infinity=True).map(repr),
                    st.integers(-10**20, 10**20).map(str))
small_numbers = st.one_of(st.sampled_from(["0", "1", "-1", "0.5", "2", "10"]), numbers)


def words(n_min, n_max, elements=small_numbers):
    return st.lists(elements, min_size=n_min, max_size=n_max).map(" ".join)


def run_cli(argv: list, out: Path) -> tuple:
    """(exit code, stderr) of ``main(argv)``; ``out`` holds EARLIER beforehand."""
    out.write_bytes(EARLIER)
    err, sink = io.StringIO(), io.StringIO()
    with redirect_stderr(err), redirect_stdout(sink), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:  # command-line mistakes leave as argparse's do
            code = exc.code
    # A warning the CLI let through would be more lines on the user's stderr.
    shown = "".join(f"{w.filename}:{w.lineno}: {w.category.__name__}: {w.message}\n" for w in caught)
    return code, shown + err.getvalue()


def assert_promise(code: int, err: str, out: Path) -> None:
    assert "Traceback" not in err, err
    assert code in (0, 2), (code, err)
    errors = [line for line in err.splitlines() if line.startswith("packetrt: error: ")]
    if code == 2:
        assert err.splitlines() == errors and len(errors) == 1, err
        assert out.read_bytes() == EARLIER  # a failed run never touches the earlier output
    else:
        assert not errors
        from PIL import Image

        with Image.open(out) as image:  # a whole PNG
            image.verify()
    assert not [p.name for p in out.parent.iterdir() if ".tmp" in p.name]
    # Memory stays bounded: the process's peak (numba, trimesh and all) never nears what an
    # unchecked size would allocate.
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss < PEAK_KIB


def render(scene: Path, tmp: Path, *extra) -> None:
    out = tmp / "out.png"
    code, err = run_cli(["render", "--scene", scene, *SMALL, "-o", out, *extra], out)
    assert_promise(code, err, out)


@pytest.fixture
def fresh(tmp_path_factory):
    """A new empty folder per example (hypothesis runs many examples in one test call)."""
    def make():
        return tmp_path_factory.mktemp("fuzz")
    return make


# -- OBJ + MTL -----------------------------------------------------------------------------------
obj_line = st.one_of(
    st.tuples(st.just("v"), words(0, 5, numbers)),
    st.tuples(st.just("v"), words(3, 3)),
    st.tuples(st.just("vt"), words(0, 3)),
    st.tuples(st.just("vn"), words(0, 4)),
    st.tuples(st.just("f"), words(0, 5, st.one_of(st.integers(-6, 6).map(str), st.sampled_from(["1/1", "2//2", "x", "1/", "/"])))),
    st.tuples(st.sampled_from(["mtllib", "usemtl", "o", "g", "s"]), st.sampled_from(["", "m.mtl", "gone.mtl", "a b", "a"])),
).map(" ".join)
mtl_line = st.one_of(
    st.tuples(st.sampled_from(["Ka", "Kd", "Ks", "Ns", "Ni", "d", "Tr", "illum"]), words(0, 4, numbers)),
    st.tuples(st.sampled_from(["newmtl", "map_Kd"]), st.sampled_from(["", "a", "tex.png", "gone.png", "bad.png"])),
).map(" ".join)
GOOD_OBJ = ["v 0 0 0", "v 1 0 0", "v 0 1 0", "vt 0 0", "vt 1 0", "vt 0 1", "mtllib m.mtl", "usemtl a", "f 1/1 2/2 3/3"]


@given(st.lists(obj_line, max_size=12), st.lists(mtl_line, max_size=10), st.booleans())
def test_obj_and_mtl(fresh, extra_obj, mtl, keep_good):
    tmp = fresh()
    (tmp / "m.mtl").write_text("newmtl a\n" + "\n".join(mtl) + "\n")
    (tmp / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    from PIL import Image

    Image.new("RGB", (2, 2), (200, 10, 10)).save(tmp / "tex.png")
    lines = (GOOD_OBJ if keep_good else []) + extra_obj
    (tmp / "s.obj").write_text("\n".join(lines) + "\n")
    render(tmp / "s.obj", tmp)


# -- PLY -----------------------------------------------------------------------------------------
@given(st.integers(-2, 5), st.integers(-2, 4), st.lists(words(0, 5, numbers), max_size=10), st.binary(max_size=64),
       st.booleans())
def test_ply(fresh, n_vertices, n_faces, rows, garbage, binary_tail):
    tmp = fresh()
    header = (f"ply\nformat ascii 1.0\nelement vertex {n_vertices}\nproperty float x\nproperty float y\n"
              f"property float z\nelement face {n_faces}\nproperty list uchar int vertex_indices\nend_header\n")
    body = ("\n".join(rows) + "\n").encode()
    (tmp / "s.ply").write_bytes(header.encode() + body + (garbage if binary_tail else b""))
    render(tmp / "s.ply", tmp)


# -- BART .aff -----------------------------------------------------------------------------------
aff_line = st.one_of(
    st.tuples(st.just("v from"), words(3, 3), st.just("at"), words(3, 3), st.just("up"), words(3, 3),
              st.just("angle"), words(1, 1)).map(" ".join),
    st.tuples(st.sampled_from(["l", "b", "am", "fm", "f", "s", "c", "p 3", "tt", "a", "xs", "k"]),
              words(0, 12, numbers)).map(" ".join),
    st.sampled_from(["{", "}", "i 1 other.aff", "i 1 s.aff", "x anim {", "m vertices 3 triangles 1 0 1 2"]),
)
GOOD_AFF = ["v from 0 0 5 at 0 0 0 up 0 1 0 angle 45", "l 0 0 5", "p 3 0 0 0 1 0 0 0 1 0"]


@given(st.lists(aff_line, max_size=8), st.booleans())
def test_aff(fresh, lines, keep_good):
    tmp = fresh()
    (tmp / "s.aff").write_text("\n".join((GOOD_AFF if keep_good else []) + lines) + "\n")
    render(tmp / "s.aff", tmp)


# -- TOML configs, scene parameters and command-line numbers --------------------------------------
toml_value = st.one_of(st.sampled_from(["nan", "inf", "-inf", "1e39", "0", "-1", "3", "99999999999", "1.5",
                                        '"x"', "true", "[1, 2]", "{a = 1}", "16", "1e16"]),
                       st.integers(-10**12, 10**12).map(str))
toml_key = st.sampled_from(["[render] width", "[render] height", "[render] max_depth", "[render] packet",
                            "[render] threads", "[render] leaf_size", "[render] bins", "[scene] time",
                            "[scene] checks", "[scene] subdivisions", "[options] rayspace",
                            "[options.rayspace] pair_budget", "[materials] override", "[traversal] primary",
                            "[nonsense] x", "[render] nonsense"])


@given(st.lists(st.tuples(toml_key, toml_value), max_size=4), st.binary(max_size=8))
def test_config_files(fresh, entries, prefix):
    tmp = fresh()
    tables: dict = {}
    for key, value in entries:
        section, name = key.split(" ")
        tables.setdefault(section, {})[name] = value
    text = "".join(f"{section}\n" + "".join(f"{k} = {v}\n" for k, v in keys.items()) for section, keys in tables.items())
    (tmp / "c.toml").write_bytes(prefix + text.encode())
    out = tmp / "out.png"
    code, err = run_cli(["render", tmp / "c.toml", "--size", "8x8", "--depth", "1", "-o", out], out)
    assert_promise(code, err, out)


@given(st.sampled_from(["checks", "subdivisions", "nope"]), toml_value,
       st.sampled_from(["--time", "--size", "--depth", "--packet", "--threads"]),
       st.one_of(st.sampled_from(WEIRD_WORDS + ["8x8", "0x0", "99999x99999", "8x", "x8"]), numbers))
def test_absurd_numbers_on_the_command_line(fresh, param, value, option, number):
    tmp = fresh()
    out = tmp / "out.png"
    argv = ["render", "--param", f"{param}={value}", *SMALL, option, number, "-o", out]
    code, err = run_cli(argv, out)
    assert_promise(code, err, out)


# -- the Python API's arguments ------------------------------------------------------------------
import numpy as np  # noqa: E402

ODD_VALUES = st.one_of(st.sampled_from([None, True, False, "", "8", "x", "partition", "general", "cpu", 8.0, 1.5,
                                        float("nan"), float("inf"), -1, 0, 1, 2, 3, 4, 8, 16, 32, 256, 10**19,
                                        np.int64(8), np.float32(4), np.bool_(True), [8], (4,), {"a": 1},
                                        b"8", 1j]),
                       st.integers(-10**6, 10**6), st.floats(allow_nan=True, allow_infinity=True),
                       st.text(max_size=6))
TRACER_ARGUMENTS = ["traversal", "frustum", "packet", "threads", "leaf_size", "bins"]
INTERSECTOR_ARGUMENTS = ["leaf_size", "bins", "order", "threads"]


def made_or_refused(make, query):
    """``make()`` answers a query, or refuses in one line as a packetrt error (a ValueError, or
    also a TypeError for a wrong type): never numba's typing errors, Python's own comparison
    TypeErrors or a mesh silently built wrong (what session 37's hand sweep found)."""
    from engine.core.errors import PacketrtError

    try:
        made = make()
    except PacketrtError as exc:
        assert "\n" not in str(exc) and str(exc), repr(exc)
        return
    assert query(made) == [4]


@given(st.sampled_from(TRACER_ARGUMENTS), ODD_VALUES)
@example("packet", 8.0).via("session 37: kept, then numba's TypingError at the first query")
@example("leaf_size", "4").via("session 37: Python's comparison TypeError")
@example("traversal", [8]).via("session 37 (profile long): 'unhashable type: list' in the registry")
def test_ray_tracer_arguments(argument, value):
    import trimesh
    from engine import RayTracer

    box = trimesh.creation.box()
    made_or_refused(lambda: RayTracer(box, **{argument: value}),
                    lambda tracer: tracer.intersects_first([[0.1, 0.2, 5]], [[0, 0, -1]]).tolist())


@given(st.sampled_from(INTERSECTOR_ARGUMENTS), ODD_VALUES)
def test_intersector_arguments(argument, value):
    import trimesh
    from engine import RayMeshIntersector

    box = trimesh.creation.box()
    made_or_refused(lambda: RayMeshIntersector(box, **{argument: value}),
                    lambda intersector: intersector.intersects_first([[0.1, 0.2, 5]], [[0, 0, -1]]).tolist())


@given(st.sampled_from(["tmin", "tmax", "multiple_hits", "max_hits", "return_locations"]), ODD_VALUES)
def test_query_keywords(keyword, value):
    """A query's keywords: answered or refused in one line, on both faces of the API."""
    import trimesh
    from engine import RayMeshIntersector, RayTracer
    from engine.core.errors import PacketrtError

    box = trimesh.creation.box()
    origin, direction = [[0.1, 0.2, 5]], [[0, 0, -1]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a bad ray is a counted miss (BadRayWarning), not a failure
        try:
            if keyword in ("tmin", "tmax"):
                RayTracer(box).intersect(origin, direction, **{keyword: value})
            else:
                RayMeshIntersector(box).intersects_id(origin, direction, **{keyword: value})
        except PacketrtError as exc:
            assert "\n" not in str(exc) and str(exc), repr(exc)

"""The Python API's thread counts hold for one call: a query on N threads runs its kernels on N
and gives the caller's numba thread count back (``engine.core.threads``). Before, a
``RayTracer(mesh, threads=1)`` query left numba on one thread for everything after it."""
import copy
import pickle

import numba
import numpy as np
import pytest
import trimesh

import engine.query.intersector as intersector_module
from engine import RayMeshIntersector, RayTracer
from engine.core.threads import numba_threads
from engine.query.errors import QueryInputError, QueryTypeError

needs_two_threads = pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs 2 numba threads")


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=2)


def rays(n=500):
    rng = np.random.default_rng(4)
    origins = rng.uniform(-3, 3, size=(n, 3))
    return origins, rng.uniform(-0.5, 0.5, size=(n, 3)) - origins


@pytest.fixture
def callers_count():
    """The test runs with numba on one thread fewer than all (at least 1) and checks it is kept."""
    before = numba.get_num_threads()
    mine = max(1, numba.config.NUMBA_NUM_THREADS - 1)
    numba.set_num_threads(mine)
    yield mine
    numba.set_num_threads(before)


def test_numba_threads_sets_the_count_inside_and_restores_it(callers_count):
    with numba_threads(1):
        assert numba.get_num_threads() == 1
    assert numba.get_num_threads() == callers_count
    with numba_threads(0):  # 0: all numba started with
        assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS
    with numba_threads(10**6):  # more than there are: all
        assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS
    with pytest.raises(RuntimeError):
        with numba_threads(1):
            raise RuntimeError("inside")
    assert numba.get_num_threads() == callers_count


@needs_two_threads
def test_ray_tracer_queries_and_renders_leave_the_callers_count(sphere, callers_count):
    origins, directions = rays()
    one = RayTracer(sphere, threads=1)
    every = RayTracer(sphere, threads=0)
    hits = one.intersect(origins, directions)
    assert numba.get_num_threads() == callers_count
    assert np.array_equal(every.intersect(origins, directions).prim, hits.prim)
    assert numba.get_num_threads() == callers_count
    one.occluded(origins, directions)
    assert numba.get_num_threads() == callers_count
    one.render({"render": {"width": 16, "height": 16, "threads": 1}})
    assert numba.get_num_threads() == callers_count


@needs_two_threads
@pytest.mark.parametrize("threads", [0, 1])
def test_mesh_intersector_queries_run_on_its_threads_and_leave_the_callers_count(sphere, callers_count,
                                                                                monkeypatch, threads):
    seen = []
    for name in ("first_hit_kernel", "collect_hits_kernel", "contains_kernel"):
        kernel = getattr(intersector_module, name)
        monkeypatch.setattr(intersector_module, name,
                            lambda *a, _k=kernel: seen.append(numba.get_num_threads()) or _k(*a))
    ours = RayMeshIntersector(sphere, threads=threads)
    origins, directions = rays()
    first = ours.intersects_first(origins, directions)
    every = ours.intersects_id(origins, directions)
    ours.intersects_any(origins, directions)
    ours.contains_points(origins)
    expected = threads or numba.config.NUMBA_NUM_THREADS
    assert len(seen) == 4 and set(seen) == {expected}
    assert numba.get_num_threads() == callers_count
    assert np.array_equal(first, RayMeshIntersector(sphere).intersects_first(origins, directions))
    assert all(np.array_equal(a, b) for a, b in zip(every, RayMeshIntersector(sphere).intersects_id(origins,
                                                                                                   directions)))


def test_mesh_intersector_keeps_threads_through_copy_and_pickle(sphere):
    ours = RayMeshIntersector(sphere, threads=1)
    for other in (copy.copy(ours), copy.deepcopy(ours), pickle.loads(pickle.dumps(ours))):
        assert other.threads == 1
    state = pickle.loads(pickle.dumps(ours)).__getstate__()
    state.pop("threads")  # an intersector pickled before the option existed
    older = RayMeshIntersector.__new__(RayMeshIntersector)
    older.__setstate__(state)
    assert older.threads == 0


@pytest.mark.parametrize("threads,error", [(-1, QueryInputError), (1.5, QueryTypeError), (True, QueryTypeError),
                                           ("2", QueryTypeError)])
def test_bad_thread_counts_are_named(sphere, threads, error):
    with pytest.raises(error, match="threads"):
        RayMeshIntersector(sphere, threads=threads)
    assert issubclass(error, ValueError)

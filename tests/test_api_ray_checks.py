"""The API's ray checks: one parallel pass (``count_invalid_rays``) decides, and only bad input
runs the numpy checks (``explain_bad_rays``), so every error is the one the numpy checks name."""
import numpy as np
import pytest

import engine.api as api
from engine.api import RayInputError, check_rays, count_invalid_rays, explain_bad_rays


def good_rays(n=64, seed=5):
    rng = np.random.default_rng(seed)
    return rng.uniform(-5, 5, (n, 3)).astype(np.float32), rng.normal(size=(n, 3)).astype(np.float32)


def spoilt(what):
    """(origins, directions, tmin, tmax) with one kind of fault at rows 7 and 40."""
    org, dirs = good_rays()
    tmin, tmax = np.zeros(64, np.float32), np.full(64, np.inf, np.float32)
    rows = [7, 40]
    if what == "nan origin":
        org[rows, 1] = np.nan
    elif what == "inf direction":
        dirs[rows, 2] = np.inf
    elif what == "zero direction":
        dirs[rows] = 0
    elif what == "tiny direction":
        dirs[rows] = 1e-30
    elif what == "huge direction":
        dirs[rows] = 1e30
    elif what == "negative tmin":
        tmin[rows] = -1
    elif what == "infinite tmin":
        tmin[rows] = np.inf
    elif what == "tmax below tmin":
        tmin[rows], tmax[rows] = 2, 1
    elif what == "nan tmax":
        tmax[rows] = np.nan
    elif what == "float64 overflow":
        org = org.astype(np.float64)
        org[rows, 0] = 1e300
    return org, dirs, tmin, tmax


FAULTS = ["nan origin", "inf direction", "zero direction", "tiny direction", "huge direction", "negative tmin",
          "infinite tmin", "tmax below tmin", "nan tmax", "float64 overflow"]


def raised(function, *args):
    with pytest.raises(RayInputError) as error:
        function(*args)
    return type(error.value), str(error.value)


@pytest.mark.parametrize("what", FAULTS)
def test_a_fault_is_counted_and_named_as_the_numpy_checks_name_it(what):
    org, dirs, tmin, tmax = spoilt(what)
    assert raised(check_rays, org, dirs, tmin, tmax) == raised(explain_bad_rays, org, dirs, tmin, tmax)
    assert "[7]" in raised(check_rays, org, dirs, tmin, tmax)[1]
    if what not in ("nan tmax", "float64 overflow"):  # refused before the pass: NaN bound, no float32
        assert count_invalid_rays(org, dirs, tmin, tmax, api.MIN_DIRECTION_LENGTH, api.MAX_DIRECTION_LENGTH) == 2


@pytest.mark.parametrize("bad", [np.zeros((4, 2)), "rays", [[1, 2, 3]] * 3])
def test_malformed_arrays_get_the_numpy_checks_errors(bad):
    org, dirs = good_rays(4)
    assert raised(check_rays, bad, dirs) == raised(explain_bad_rays, bad, dirs)
    assert raised(check_rays, org, bad) == raised(explain_bad_rays, org, bad)


def test_good_rays_take_the_one_pass_and_equal_the_numpy_checks(monkeypatch):
    org, dirs = good_rays()
    tmax = np.linspace(1, 9, 64)
    cases = [(org, dirs, None, None), (org, dirs, 0.5, tmax), (org.astype(np.float64).tolist(), dirs, 0, 3.0),
             (org[:0], dirs[:0], None, None)]
    expected = [explain_bad_rays(*case) for case in cases]
    monkeypatch.setattr(api, "explain_bad_rays", lambda *a: pytest.fail("good rays ran the numpy checks"))
    for case, want in zip(cases, expected):
        got = check_rays(*case)
        assert all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in zip(got, want))

"""engine.query.local8: the eight-lane step of ``packet_lanes`` writes the bits of the lane-by-lane
loop (which runs where the input rows are not contiguous) in every lane: good rays, padding rows,
NaN and infinite components, zero directions, origins too far out for float32, directions
along an axis (zero components: the inverse's sign), and the ``ok`` flag of every input ray."""
from __future__ import annotations

import numpy as np

from engine.query.coherent import packet_lanes


def run(origins, directions, rows, lanes):
    center = np.array([0.25, -1.5, 3.0])
    org, dirs, inv = (np.full((lanes, 3), 7, np.float32) for _ in range(3))
    tmin, tmax = np.full(lanes, 7, np.float32), np.full(lanes, 7, np.float32)
    ok = np.ones(origins.shape[0], np.bool_)
    packet_lanes(origins, directions, center, 3.7, rows, org, dirs, inv, tmin, tmax, ok)
    return org, dirs, inv, tmin, tmax, ok


def scattered(a):
    """``a`` as a view whose rows are not contiguous (the lane-by-lane path)."""
    block = np.zeros(a.shape + (2,), a.dtype)
    block[..., 0] = a
    return block[..., 0]


def test_eight_lanes_at_a_time_give_the_lane_by_lane_bits():
    rng = np.random.default_rng(3)
    n, lanes = 500, 515  # a tail of lanes past the rows, and rows past a multiple of eight
    origins = rng.normal(size=(n, 3)) * 50
    directions = rng.normal(size=(n, 3))
    directions[3] = 0.0                     # zero direction: bad
    directions[4, 1] = np.nan               # NaN: bad
    origins[5, 2] = np.inf                  # infinite origin: bad
    origins[6, 0] = 1e40                    # too far out for float32: bad
    directions[7] = (0.0, -2.0, 0.0)        # along -y: inverse +-HUGE on x and z
    directions[8] = (-0.0, 0.0, 3.0)        # a negative zero component
    directions[9] = (1e-300, 1e-300, 0.0)   # tiny: its length underflows to 0 in float64 squares
    rows = rng.permutation(np.concatenate([np.arange(n), -np.ones(11, np.int64)]))[:lanes - 8].astype(np.int64)
    rows = np.concatenate([rows[:24], np.arange(3, 11), rows[24:]])  # the edge rays side by side
    wide = run(origins, directions, rows, lanes)
    narrow = run(scattered(origins), scattered(directions), rows, lanes)
    for a, b in zip(wide, narrow):
        assert np.array_equal(a.view(np.uint8), b.view(np.uint8))
    org, dirs, inv, tmin, tmax, ok = wide
    assert not ok[[3, 4, 5, 6, 9]].any() and ok[[7, 8]].all() and ok.sum() == n - 5
    dead = tmin > tmax
    assert dead.sum() == np.count_nonzero(rows < 0) + 5 * 2 + (lanes - len(rows))  # each edge ray twice
    assert (dirs[dead] == (0, 0, 1)).all() and (org[dead] == 0).all()
    lane = 24 + 4  # ray 7, along -y
    assert inv[lane, 0] > 1e29 and inv[lane, 2] > 1e29 and inv[lane, 1] == -1.0


def test_intrinsic_argument_checks_name_the_wrong_argument():
    import pytest
    from numba import types
    from numba.core.errors import TypingError

    from engine.core.lanes8 import check_arguments

    array = types.Array(types.float64, 2, "C")
    check_arguments(("origins", "start"), (array, types.int64), {"start": types.Integer})
    with pytest.raises(TypingError, match="start must be an integer"):
        check_arguments(("origins", "start"), (array, types.float64), {"start": types.Integer})
    with pytest.raises(TypingError, match="origins must be an array"):
        check_arguments(("origins", "start"), (types.int64, types.int64), {"start": types.Integer})

"""``engine.core.scratch.Scratch``: reused per-lane buffers, and constant inputs filled once."""
import numpy as np

from engine.core.scratch import Scratch


def test_take_returns_the_same_memory_for_the_same_key():
    scratch = Scratch()
    first = scratch.take("a", 100, (3,))
    assert first.shape == (100, 3) and first.dtype == np.float32
    again = scratch.take("a", 90, (3,))
    assert np.shares_memory(first, again)
    assert not np.shares_memory(first, scratch.take("b", 100, (3,)))


def test_a_constant_holds_its_value_in_every_row_however_it_grows_or_changes():
    scratch = Scratch()
    ones = scratch.constant("w", 10, 1.0, (3,))
    assert ones.shape == (10, 3) and np.all(ones == 1)
    # Within the buffer's room: the same memory, not written again, still all ones.
    ones[0, 0] = 5.0  # (a caller must not do this; here it shows that no fill happened)
    assert scratch.constant("w", 11, 1.0, (3,))[0, 0] == 5.0
    ones[0, 0] = 1.0
    # Grown past its room: a new buffer, filled.
    grown = scratch.constant("w", 1000, 1.0, (3,))
    assert grown.shape == (1000, 3) and np.all(grown == 1)
    # Another value under the same key: filled with it.
    assert np.all(scratch.constant("w", 1000, np.inf, (3,)) == np.inf)
    # A key's rows taken by ``take`` (uninitialised, maybe written) and then as a constant are
    # filled again, even with the value it held before.
    scratch.take("t", 50)[:] = 7.0
    assert np.all(scratch.constant("t", 50, 0.0) == 0.0)
    scratch.take("t", 50)[:] = 7.0
    assert np.all(scratch.constant("t", 50, 0.0) == 0.0)


def test_a_new_buffer_has_every_page_written(monkeypatch):
    """A new buffer is written through once before it is handed out, so that its pages are
    present: the eight-lane steps store some rows through a lane mask, and a masked store with
    every lane off into a page never written costs a microcode assist each time on this machine
    (the bunny's light_directions: 13-16 ms a frame instead of 2.0-2.5). Seen here through an
    ``np.empty`` that hands out garbage: none of it may reach the caller."""
    import engine.core.scratch as scratch_module

    real_empty = np.empty
    monkeypatch.setattr(scratch_module.np, "empty", lambda shape, dtype=float: np.full(shape, 7, dtype))
    try:
        view = scratch_module.Scratch().take("k", 1000, (3,), np.float32)
    finally:
        monkeypatch.setattr(scratch_module.np, "empty", real_empty)
    assert view.shape == (1000, 3) and not view.any()

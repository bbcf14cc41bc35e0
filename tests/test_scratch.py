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
    """A new buffer gets a store in every page it spans before it is handed out, so that its
    pages are present: the eight-lane steps store some rows through a lane mask, and a masked
    store with every lane off into a page never written costs a microcode assist each time on
    this machine (the bunny's light_directions: 13-16 ms a frame instead of 2.0-2.5). Seen
    here through an ``np.empty`` that hands out garbage (7s): each page the buffer spans must
    hold a byte the scratch wrote, for a buffer touched serially and one touched in parallel,
    neither starting on a page boundary."""
    import engine.core.scratch as scratch_module

    real_empty = np.empty

    def garbage(shape, dtype=float):
        # Over-allocate and start 100 bytes into a page, as malloc's buffers may.
        count = int(np.prod(shape)) * np.dtype(dtype).itemsize
        raw = np.full(count + 2 * scratch_module.PAGE, 7, np.uint8)
        start = (-raw.ctypes.data) % scratch_module.PAGE + 100
        return raw[start:start + count].view(dtype).reshape(shape)

    monkeypatch.setattr(scratch_module.np, "empty", garbage)
    try:
        scratch = scratch_module.Scratch()
        # Sizes whose last page holds only the buffer's last few bytes, beyond its last
        # page-spaced store (16,288 bytes from offset 100; 1,769,472): a numpy pass, a numba one.
        small = scratch.take("small", 14479, (), np.uint8)
        large = scratch.take("large", scratch_module.SERIAL_TOUCH_BYTES // 8, (3,))
    finally:
        monkeypatch.setattr(scratch_module.np, "empty", real_empty)
    assert small.shape == (14479,) and large.shape == (scratch_module.SERIAL_TOUCH_BYTES // 8, 3)
    for key in ("small", "large"):
        buffer = scratch._buffers[key]   # the whole buffer, with its room beyond the rows taken
        flat = buffer.reshape(-1).view(np.uint8)
        pages = (buffer.ctypes.data + np.arange(flat.shape[0])) // scratch_module.PAGE
        written = np.zeros(pages.max() - pages.min() + 1, bool)
        written[pages[flat == 0] - pages.min()] = True
        assert written.all(), f"{(~written).sum()} of {written.size} pages never written"
        assert (flat == 7).mean() > 0.99  # one store a page, not a fill

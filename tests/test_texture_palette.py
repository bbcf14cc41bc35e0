"""Textures are stored as a palette index per texel (engine.render.materials.texture_palette):
every texel must come back bit for bit, and 8-bit images must take one byte per channel."""
import numpy as np

from engine.render.materials import BYTE_PALETTE, texture_palette


def _stacked(textures):
    return np.concatenate([np.asarray(t, np.float32).reshape(-1, 3) for t in textures])


def test_byte_textures_take_one_byte_per_channel_and_come_back_exactly():
    rng = np.random.default_rng(1)
    textures = [rng.integers(0, 256, (5, 7, 3)).astype(np.float32) / 255.0,
                rng.integers(0, 256, (3, 2, 3)).astype(np.float32) / 255.0]
    index, palette = texture_palette(textures)
    assert index.dtype == np.uint8 and index.shape == (41, 3)
    assert palette is BYTE_PALETTE
    np.testing.assert_array_equal(palette[index], _stacked(textures))


def test_float_textures_keep_every_value():
    rng = np.random.default_rng(2)
    few = rng.random((4, 4, 3), dtype=np.float32).round(1)          # 11 distinct values, not k/255
    index, palette = texture_palette([few])
    assert index.dtype == np.uint8
    assert (palette[index].view(np.uint32) == _stacked([few]).view(np.uint32)).all()
    many = rng.random((40, 40, 3), dtype=np.float32)                 # 4800 distinct values
    index, palette = texture_palette([few, many])
    assert index.dtype == np.uint16
    assert (palette[index].view(np.uint32) == _stacked([few, many]).view(np.uint32)).all()


def test_values_outside_the_unit_range_are_not_clipped():
    texture = np.full((1, 2, 3), 2.0, np.float32)
    texture[0, 0] = -0.5
    index, palette = texture_palette([texture])
    np.testing.assert_array_equal(palette[index], _stacked([texture]))

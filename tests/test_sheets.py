"""Contact sheets (render/sheets.py): tile sizes, row layout, labels that leave inputs alone."""

import numpy as np
import pytest

from egorelight_cli.render.sheets import MAX_WIDTH, contact_sheet, fit_tile, label, labelled_rows, stack_rows, tile_row


def test_fit_tile_keeps_the_aspect_and_makes_rgb():
    grey = np.full((50, 100), 7, np.uint8)
    assert fit_tile(grey, height=20).shape == (20, 40, 3)
    rgba = np.zeros((40, 30, 4), np.uint8)
    rgba[..., 3] = 255
    tile = fit_tile(rgba, width=15)
    assert tile.shape == (20, 15, 3) and tile.max() == 0  # alpha dropped, not read as blue
    with pytest.raises(ValueError):
        fit_tile(grey)
    with pytest.raises(ValueError):
        fit_tile(grey, height=10, width=10)


def test_label_draws_on_a_copy():
    image = np.zeros((30, 80, 3), np.uint8)
    out = label(image, "abc")
    assert image.max() == 0 and out.max() > 0
    assert out.flags.c_contiguous
    assert np.array_equal(label(image, ""), image)


def test_rows_are_padded_bottom_and_right():
    row = tile_row([("a", np.zeros((10, 10, 3), np.uint8)), ("b", np.zeros((10, 40, 3), np.uint8))], width=20)
    assert row.shape == (20, 40, 3)  # 20x20 and 5x20 tiles; the short one padded below
    sheet = stack_rows([np.ones((5, 10, 3), np.uint8), np.ones((7, 30, 3), np.uint8)])
    assert sheet.shape == (12, 30, 3)
    assert sheet[:5, 10:].max() == 0 and sheet[:5, :10].min() == 1


def test_contact_sheet_has_a_title_bar_and_a_row_per_non_empty_entry():
    tile = np.full((32, 64, 3), 200, np.uint8)
    sheet = contact_sheet([[("x", tile), ("y", tile)], [], [("z", tile)]], title="t", tile_height=16)
    assert sheet.shape == (22 + 16 + 16, 64, 3)
    wide = contact_sheet([[("w", np.zeros((10, 10 * MAX_WIDTH, 3), np.uint8))]], tile_height=10)
    assert wide.shape == (10, MAX_WIDTH, 3)
    assert contact_sheet([[]], title="nothing", tile_height=16).shape[0] == 22 + 16


def test_labelled_rows_write_the_label_across_the_row():
    tiles = [np.zeros((20, 20, 3), np.uint8)] * 3
    long_label = "a label longer than one tile"
    sheet = labelled_rows([(long_label, tiles), ("b", tiles[:1])], tile_width=20)
    assert sheet.shape == (40, 60, 3)
    assert sheet[:20, 20:].max() > 0  # the text goes on past the first tile
    assert stack_rows([np.zeros((1, 2, 3), np.uint8), np.zeros((1, 5, 3), np.uint8)], fill=255)[0, 2:].min() == 255
    with pytest.raises(ValueError, match="uint8"):
        label(np.zeros((4, 4, 3), np.float32), "x")

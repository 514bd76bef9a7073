"""Placing the sky/snow boundary by colour (appliance.vision.skyline_snow.colour_rows)."""

from __future__ import annotations

import numpy as np

from appliance.vision.skyline_snow import colour_rows


def boundary_image(boundary_row: float, sky: float = 0.14, ground: float = 0.04, h: int = 60,
                   w: int = 4) -> np.ndarray:
    """Blue minus red per pixel: ``sky`` above ``boundary_row`` (pixel edges at half rows), ``ground``
    below, the pixel the boundary crosses mixed by its share of each."""
    top = np.arange(h) - 0.5
    share_sky = np.clip(boundary_row - top, 0.0, 1.0)
    col = ground + (sky - ground) * share_sky
    return np.repeat(col[:, None], w, axis=1).astype(np.float32)


def test_a_line_two_rows_off_moves_to_the_colour_step() -> None:
    chroma = boundary_image(30.3)
    got = colour_rows(chroma, np.array([28.0, 32.0, 30.0, np.nan]))
    # the halfway crossing of a step at 30.3 lies in the pixel it cuts: between rows 29.8 and 30.8
    assert np.all(np.abs(got[:3] - 30.3) <= 0.5)
    assert np.isnan(got[3])


def test_no_colour_step_leaves_the_line_where_it_was() -> None:
    chroma = boundary_image(30.3, sky=0.06, ground=0.05)
    rows = np.array([28.0, 32.0, 30.0, 31.0])
    assert np.array_equal(colour_rows(chroma, rows), rows)


def test_a_step_beyond_reach_leaves_the_line_where_it_was() -> None:
    chroma = boundary_image(20.0)
    rows = np.array([30.0, 30.0, 30.0, 30.0])
    assert np.array_equal(colour_rows(chroma, rows), rows)

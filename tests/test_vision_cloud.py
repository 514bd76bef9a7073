"""What the detector takes for white cloud just above a line (appliance.vision.skyline_edges.cloud_above)."""

from __future__ import annotations

import numpy as np

from appliance.vision.skyline_edges import anchored, cloud_above

GRASS = (40, 75, 55)  # BGR: dark and warm
CLOUD = (238, 236, 232)  # white, a little blue
CLOUD_BASE = (150, 146, 142)  # the grey base of a cumulus
HAZY_LAND = (205, 175, 150)  # far land through haze: as blue as the sky's horizon
SKY = (230, 180, 140)
ROCK_SHADOW = (60, 62, 66)


def column(*bands: tuple[tuple[int, int, int], int]) -> np.ndarray:
    """A 1-column BGR image stacked from (colour, rows) bands, top first, widened to 5 columns."""
    rows = [np.tile(np.array(c, np.uint8), (n, 1)) for c, n in bands]
    return np.repeat(np.concatenate(rows)[:, None, :], 5, axis=1)


def test_white_and_grey_cloud_over_grass_is_cloud() -> None:
    img = column((SKY, 10), (CLOUD, 10), (CLOUD_BASE, 5), (GRASS, 20))
    assert cloud_above(img, np.full(5, 25.0)).all()


def test_clear_sky_alone_over_grass_is_not_white_cloud() -> None:
    img = column((SKY, 25), (GRASS, 20))
    assert not cloud_above(img, np.full(5, 25.0)).any()


def test_hazy_land_above_a_near_hill_is_not_cloud() -> None:
    img = column((SKY, 10), (HAZY_LAND, 15), (GRASS, 20))
    assert not cloud_above(img, np.full(5, 25.0)).any()


def test_a_shadow_among_the_rows_above_makes_it_a_rock_not_a_cloud() -> None:
    img = column((CLOUD, 16), (ROCK_SHADOW, 2), (CLOUD, 7), (GRASS, 20))
    assert not cloud_above(img, np.full(5, 25.0)).any()


def test_white_over_white_is_not_cloud_over_ground() -> None:
    img = column((CLOUD, 25), (CLOUD, 20))
    assert not cloud_above(img, np.full(5, 25.0)).any()


def test_no_line_or_a_line_too_near_the_edge_is_not_judged() -> None:
    img = column((CLOUD, 25), (GRASS, 20))
    got = cloud_above(img, np.array([np.nan, 5.0, 25.0, 40.0, np.nan]))
    assert got.tolist() == [False, False, True, False, False]


def test_a_cloud_stretch_joining_the_clear_sky_line_on_both_sides_is_kept() -> None:
    # columns 0-9 good, 10-19 cloud above (12-13 untrusted but still under the cloud), 20-29 good
    good = np.r_[np.ones(10, bool), np.zeros(10, bool), np.ones(10, bool)]
    links = ~good
    extra = links.copy()
    extra[12:14] = False
    rows = np.full(30, 50.0)
    got = anchored(extra, good, links, rows, gap_px=3, max_step_px=4.0, wrap=False)
    assert got.tolist() == extra.tolist()


def test_a_stretch_cut_off_from_the_line_or_off_its_rows_is_dropped() -> None:
    good = np.r_[np.ones(10, bool), np.zeros(30, bool), np.ones(10, bool)]
    extra = np.zeros(50, bool)
    extra[20:25] = True  # a shadow's edge inside a rock: the rock's dark parts (no link) around it
    rows = np.full(50, 50.0)
    assert not anchored(extra, good, extra, rows, gap_px=3, max_step_px=4.0, wrap=False).any()
    # joined by links, but meeting the line on one side 10 rows off it
    links = ~good
    rows[35:40] = 60.0
    extra[20:40] = True
    assert not anchored(extra, good, links, rows, gap_px=3, max_step_px=4.0, wrap=False).any()


def test_a_cloud_stretch_across_the_seam_of_a_full_circle_is_joined() -> None:
    good = np.zeros(40, bool)
    good[5:35] = True
    extra = ~good  # columns 35-39 and 0-4: across the seam
    rows = np.full(40, 50.0)
    assert anchored(extra, good, extra, rows, gap_px=3, max_step_px=4.0, wrap=True).tolist() == extra.tolist()
    assert not anchored(extra, good, extra, rows, gap_px=3, max_step_px=4.0, wrap=False).any()


def test_the_second_paths_stretches_each_hold_one_pinned_column_either_side() -> None:
    from appliance.vision.skyline_detect import _stretches

    free = np.array([1, 1, 0, 0, 1, 1, 1, 0, 1], dtype=bool)
    # a full circle: the run 8, 0, 1 crosses the seam, bounded by the columns 7 and 2
    got = sorted(tuple(s.tolist()) for s in _stretches(free, wrap=True))
    assert got == [(3, 4, 5, 6, 7), (7, 8, 0, 1, 2)]
    # a partial panorama: the image's ends bound the runs
    got = sorted(tuple(s.tolist()) for s in _stretches(free, wrap=False))
    assert got == [(0, 1, 2), (3, 4, 5, 6, 7), (7, 8)]
    assert [s.tolist() for s in _stretches(np.ones(4, bool), wrap=True)] == [[0, 1, 2, 3]]

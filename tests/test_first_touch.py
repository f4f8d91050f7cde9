"""``vastray.sim.first_touch``: what a fresh node pays to touch its memory for the first
time, measured in fresh processes rendering a store."""

from __future__ import annotations

import pytest

from vastray.scene.errors import InputError
from vastray.scene.generate import generate
from vastray.sim import first_touch


def test_pages_per_path_is_the_slope_over_sizes_never_negative():
    assert first_touch.pages_per_path([(100, 70), (300, 170), (100, 70), (300, 170)]) == \
        pytest.approx(0.5)
    assert first_touch.pages_per_path([(100, 70), (100, 90)]) == 0.0  # one size: no slope
    assert first_touch.pages_per_path([(100, 90), (300, 50)]) == 0.0  # noise: nothing
    assert first_touch.pages_per_path([]) == 0.0


def test_a_page_fault_costs_some_microseconds_here():
    assert 1e-8 < first_touch.page_fault_seconds(megabytes=8) < 1e-4


def test_a_fresh_process_touches_more_pages_for_more_paths(tmp_path):
    store = tmp_path / "rm.store"
    generate("rm", store, 24, grid=(2, 1, 1))
    tile_paths, tile_pages = first_touch.fresh_pages(str(store), quick=True, tile=True)
    paths, pages = first_touch.fresh_pages(str(store), quick=True, tile=False)
    assert paths == 4 * tile_paths  # twice the width and height
    assert 0 < tile_pages < pages
    slope = first_touch.pages_per_path([(tile_paths, tile_pages), (paths, pages)])
    assert 0.01 < slope < 8.0  # a path's arrays: a fraction of a page to a few


def test_a_measurement_of_a_missing_store_names_it(tmp_path):
    missing = tmp_path / "nothing.store"
    with pytest.raises(InputError, match="nothing.store"):
        first_touch.fresh_pages(str(missing), quick=True, tile=True)

"""The refinement configuration: its checks, and which settings its digest names."""

from __future__ import annotations

import dataclasses

import pytest

from pwm.config import DEFAULTS, MODES, RefinementConfig
from pwm.photoclinometry import Solver
from pwm.weights import Rules


def test_modes_are_the_solver_modes():
    assert MODES == ("pwm", "standard")


@pytest.mark.parametrize("change, message", [
    ({"mode": "fast"}, "mode 'fast'"), ({"nodes": 4}, "at least 8"), ({"overlap": 0.9}, "overlap"),
    ({"spacing_gsd": 3.0}, "spacing"), ({"passes": 0}, "one pass"), ({"search_px": -1.0}, "non-negative"),
    ({"min_images": 0}, "at least one image"), ({"tile_radius_km": 0.0}, "positive"),
    ({"shape_window_nodes": 4}, "shape windows of 4 nodes"),
])
def test_a_bad_setting_is_refused_with_its_name(change, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(DEFAULTS, **change)


def test_the_digest_follows_what_changes_one_maplets_refinement():
    base = DEFAULTS.digest()
    assert RefinementConfig().digest() == base
    for change in ({"mode": "standard"}, {"search_px": 8.0}, {"min_images": 4}, {"shape_window_nodes": 0},
                   {"solver": Solver(slope_scale=0.2)}, {"rules": Rules(max_shadow_fraction=0.2)}):
        assert dataclasses.replace(DEFAULTS, **change).digest() != base, change
    # tiling makes other maplets, whose grids are in their own input hashes
    for change in ({"nodes": 64}, {"overlap": 0.5}, {"spacing_gsd": 0.5}, {"passes": 3}, {"tile_radius_km": 1.0}):
        assert dataclasses.replace(DEFAULTS, **change).digest() == base, change

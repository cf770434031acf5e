"""How far a maplet's solution moved between two passes (pwm.maplets.solution_change), the
measure by which a maplet settles (pwm.config.RefinementConfig.another_pass)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pwm.frames import latlon_to_unit, local_frame
from pwm.maplets import MapletGrid, flat_grid, solution_change

SPACING_KM = 1e-4


def _maplet(origin: np.ndarray, normal: np.ndarray, surface) -> MapletGrid:
    """A maplet of 41 x 41 nodes at `origin` whose heights follow surface(x, y) (km, in the
    frame of the maplet at `origin` along `normal`)."""
    grid = flat_grid("M", local_frame(origin, normal), size_km=40 * SPACING_KM, nodes=41)
    x, y = np.meshgrid(grid.axis_km, grid.axis_km)
    return dataclasses.replace(grid, heights=surface(x, y))


def test_a_solution_change_is_the_rms_height_change_in_node_spacings():
    normal = latlon_to_unit(30.0, 40.0)
    origin = 0.25 * normal

    def bumpy(x, y):
        return 3 * SPACING_KM * np.sin(x / (8 * SPACING_KM)) * np.cos(y / (5 * SPACING_KM))

    first = _maplet(origin, normal, bumpy)
    assert solution_change(first, first) == pytest.approx(0.0, abs=1e-9)
    # the same frame, node by node: the RMS of the differences
    raised = dataclasses.replace(first, heights=first.heights + 0.4 * SPACING_KM)
    assert solution_change(first, raised) == pytest.approx(0.4, abs=1e-9)
    # the same surface tiled afresh about an origin moved along the normal and tilted a little,
    # as a later pass of `pwm refine` tiles its fused model: no change, to the interpolation
    tilt = np.cross(normal, [0.0, 0.0, 1.0])
    tilted = normal + 2e-3 * tilt / np.linalg.norm(tilt)
    tilted /= np.linalg.norm(tilted)
    shift = 1.5 * SPACING_KM
    again = first.frame.to_body(np.array([[0.0, 0.0, shift]]))[0]
    retiled = _maplet(again, tilted, lambda x, y: np.zeros_like(x))
    # its heights: where the first surface lies along the new frame's z, found by iteration
    local = retiled.nodes_local()
    for _ in range(20):
        body = retiled.frame.to_body(local.reshape(-1, 3))
        on_first = first.frame.to_local(body)
        target = first.frame.to_body(np.column_stack([on_first[:, :2], bumpy(on_first[:, 0], on_first[:, 1])]))
        local = retiled.frame.to_local(target).reshape(local.shape)
        local[..., :2] = retiled.nodes_local()[..., :2]
    retiled = dataclasses.replace(retiled, heights=local[..., 2])
    assert solution_change(first, retiled) < 0.02
    assert solution_change(first, dataclasses.replace(retiled, heights=retiled.heights + SPACING_KM)) == pytest.approx(
        1.0, abs=0.05)
    # nothing of it over the earlier grid: no measure
    far = _maplet(origin + 1.0 * tilt / np.linalg.norm(tilt), normal, bumpy)
    assert solution_change(first, far) == float("inf")

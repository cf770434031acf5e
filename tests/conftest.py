"""Fixtures shared across test folders: one simulated `tiny` downlink per session."""

from __future__ import annotations

from pathlib import Path

import pytest

from pwm.simulate.campaign import simulate
from pwm.simulate.scenarios import get_scenario

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def tiny_sim(tmp_path_factory) -> Path:
    """OUT directory of `pwm simulate OUT --scenario tiny --seed 3` (downlink/ and truth/)."""
    out = tmp_path_factory.mktemp("tiny") / "sim"
    simulate(out, scenario=get_scenario("tiny"), seed=3)
    return out

"""`pwm config show`: the refinement configuration the PWM_* environment makes, with its digest."""

from __future__ import annotations

import dataclasses
import json

from typer.testing import CliRunner

from pwm.config import DEFAULTS
from pwm.knowledge import IndependentErrors
from service.cli import app


def _shown(pwm: CliRunner) -> dict:
    result = pwm.invoke(app, ["config", "show"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def test_the_defaults_are_shown_with_their_digest(pwm, tmp_path):
    shown = _shown(pwm)
    assert shown["digest"] == DEFAULTS.digest()
    refinement = shown["refinement"]
    assert refinement["mode"] == DEFAULTS.mode and refinement["passes"] == DEFAULTS.passes
    assert refinement["knowledge"] is None
    assert refinement["knowledge_sigmas"] == DEFAULTS.knowledge_sigmas
    assert refinement["placement"] == json.loads(json.dumps(dataclasses.asdict(DEFAULTS.placement)))
    assert refinement["registration"] == dataclasses.asdict(DEFAULTS.registration)
    assert refinement["solver"] == dataclasses.asdict(DEFAULTS.solver)
    assert set(refinement) == {f.name for f in dataclasses.fields(DEFAULTS)}
    assert shown["in_digest"] == sorted(DEFAULTS.digested())
    assert not (tmp_path / "data").exists()  # it opens no catalog


def test_the_environment_changes_what_is_shown_and_the_digest(pwm, monkeypatch):
    monkeypatch.setenv("PWM_REFINE_MODE", "standard")
    monkeypatch.setenv("PWM_REFINE_PASSES", "3")
    monkeypatch.setenv("PWM_REFINE_MAX_PASSES", "5")
    monkeypatch.setenv("PWM_MAPLET_NODES", "64")
    monkeypatch.setenv("PWM_POSE_KNOWLEDGE", "1,1e-4")
    shown = _shown(pwm)
    expected = dataclasses.replace(DEFAULTS, mode="standard", passes=3, max_passes=5, nodes=64,
                                   knowledge=IndependentErrors(position_m=1.0, pointing_rad=1e-4))
    assert shown["digest"] == expected.digest() != DEFAULTS.digest()
    refinement = shown["refinement"]
    assert (refinement["mode"], refinement["passes"], refinement["max_passes"], refinement["nodes"]) == (
        "standard", 3, 5, 64)
    assert refinement["knowledge"] == "1,0.0001"


def test_a_bad_setting_is_named(pwm, monkeypatch):
    monkeypatch.setenv("PWM_REFINE_PASSES", "many")
    result = pwm.invoke(app, ["config", "show"])
    assert result.exit_code == 2
    assert "PWM_REFINE_PASSES" in result.output

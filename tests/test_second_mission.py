"""A second mission through every command, with no instrument, target or frame option: a
Hayabusa2 ONC-T downlink of Ryugu (`pwm simulate --scenario ryugu-tiny`) with bad products among
its images, through `pwm ingest`, `pwm refine`, `pwm spg` and `pwm run` on a SQLite catalog.
Each command skips the bad products, says which and why on stderr (and in its JSON report
where it writes one) and goes on."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import select
from test_downlink import add_bad_products, copy_downlink
from typer.testing import CliRunner

from pwm.io.meshio import read_mesh
from pwm.raytrace import RayTracer
from pwm.simulate.truth import load as load_truth
from pwm.tiling import sample_heights, tile
from service.catalog import open_catalog
from service.cli import app
from service.rows import Image, ImageStatus
from service.settings import get_settings

# one pass over a small region keeps the refinement to seconds
NODES, RADIUS_KM = 64, 0.002
SMALL = ["--nodes", str(NODES), "--passes", "1", "--radius-km", str(RADIUS_KM)]


@pytest.fixture
def downlink(ryugu_sim, tmp_path, shared_data) -> tuple[Path, dict[str, str]]:
    """A copy of the Ryugu downlink with three bad products, and the codes they are skipped with."""
    copy = copy_downlink(ryugu_sim, tmp_path)
    return copy, add_bad_products(copy, shared_data)


@pytest.fixture
def catalog_env(tmp_path, monkeypatch) -> Path:
    """PWM_DATA_DIR set to a fresh folder: the commands' catalog is the SQLite file there."""
    data = tmp_path / "data"
    monkeypatch.setenv("PWM_DATA_DIR", str(data))
    monkeypatch.delenv("PWM_DATABASE_URL", raising=False)
    get_settings.cache_clear()
    yield data
    get_settings.cache_clear()


def invoke(*args: str):
    return CliRunner().invoke(app, [str(a) for a in args])


def reported(stderr: str, verb: str) -> dict[str, str]:
    """File name -> code of the lines '<verb> PATH: CODE: reason' on stderr."""
    return {Path(m[1]).name: m[2] for m in re.finditer(rf"^{verb} (\S+): (\w+): .+$", stderr, re.MULTILINE)}


def test_no_instrument_target_or_frame_option_is_left_with_a_mission_default():
    for command in ("refine", "spg"):
        result = invoke(command, "--help")
        assert result.exit_code == 0
        assert not re.search(r"MapCam|-64361|BENNU|IAU_BENNU|OSIRIS", result.output, re.IGNORECASE)


def test_ingest(downlink, catalog_env):
    directory, bad = downlink
    result = invoke("ingest", directory)
    assert result.exit_code == len(bad), result.output  # the exit status counts the files that failed
    assert reported(result.stderr, "rejected") == bad
    with open_catalog()() as session:
        images = session.scalars(select(Image)).all()
        accepted = [i for i in images if i.status is ImageStatus.ACCEPTED]
        assert len(accepted) == 5 and len(images) == 8
        assert {(i.instrument.naif_id, i.instrument.name, i.geometry.body_frame) for i in accepted} == {
            (-37100, "HAYABUSA2_ONC-T", "RYUGU_FIXED")}


def test_refine(downlink, ryugu_sim, tmp_path):
    directory, bad = downlink
    out = tmp_path / "refined"
    result = invoke("refine", directory, "--start", directory / "start_model.obj", "--out", out, *SMALL)
    assert result.exit_code == 0, result.output
    assert reported(result.stderr, "skipped") == bad
    report = json.loads((out / "maplets.json").read_text())
    assert {Path(s["path"]).name: s["code"] for s in report["skipped"]} == bad
    assert report["images"] == 5 and report["body_frame"] == "RYUGU_FIXED"
    assert report["instruments"] == {"-37100": "HAYABUSA2_ONC-T"}
    assert all(len(m["images"]) >= 3 for m in report["maplets"])
    # the relief over the refined maplets' nodes, common offset removed, against the truth's
    start = read_mesh(directory / "start_model.obj")
    region = report["region"]
    maplets = tile(start, spacing_km=region["spacing_km"], nodes=NODES, overlap=0.25, centre_lat_deg=region["lat_deg"],
                   centre_lon_deg=region["lon_deg"], radius_km=region["radius_km"])
    assert len(maplets) == len(report["maplets"])
    truth, refined = RayTracer(load_truth(ryugu_sim / "truth").mesh), RayTracer(read_mesh(out / "refined.ply"))
    errors = {name: np.mean([np.std(sample_heights(model, m) - sample_heights(truth, m)) for m in maplets])
              for name, model in (("start", start), ("refined", refined))}
    assert errors["refined"] < 0.85 * errors["start"], errors


def test_spg(downlink, tmp_path):
    directory, bad = downlink
    out = tmp_path / "spg"
    result = invoke("spg", directory, "--start", directory / "start_model.obj", "--out", out)
    assert result.exit_code == 0, result.output
    assert reported(result.stderr, "skipped") == bad
    stats = json.loads((out / "spg.json").read_text())
    assert {Path(s["path"]).name: s["code"] for s in stats["skipped"]} == bad
    assert stats["points"] >= 30 and stats["residual_rms_px"] < 1.5
    corrections = json.loads((out / "corrections.json").read_text())
    assert corrections["frame"] == "RYUGU_FIXED" and len(corrections["images"]) == 5


def test_run(downlink, catalog_env):
    directory, bad = downlink
    # one pass (each pass publishing a version of its own: tests/workers/test_operations.py)
    result = invoke("run", directory, "--maplet-nodes", "40", "--tile-radius-km", "0.002", "--passes", "1")
    assert result.exit_code == len(bad), result.output  # as for pwm ingest: the files that failed
    assert reported(result.stderr, "rejected") == bad
    # version 1 is the start model; the pass publishes the next
    assert "published version 2" in result.stdout

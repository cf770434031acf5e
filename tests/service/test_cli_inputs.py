"""What the `pwm` command line does with bad input: numbers that are not finite or out of range,
versions that are no version, PWM_* settings that make no valid settings, a run whose files
failed, shape models in every format `pwm export` writes, and writes that fail part way."""

from __future__ import annotations

import errno
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from pwm.io.dsk import write_dsk
from pwm.io.icq import icq_to_mesh, mesh_to_icq, read_icq, write_icq
from pwm.io.meshio import read_shape_model, write_obj, write_ply
from pwm.mesh import Mesh
from service.cli import app

PWM = Path(sys.executable).with_name("pwm")


def _said(output: str) -> str:
    """The output as one line of words: typer boxes and wraps its usage errors."""
    return " ".join(re.sub(r"[│╭╮╰╯─]", " ", output).split())


def _sphere() -> Mesh:
    """A small closed mesh about the origin (km)."""
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.25)
    return Mesh(np.asarray(ball.vertices, dtype=float), np.asarray(ball.faces, dtype=np.int64))


# -- numbers and versions ---------------------------------------------------------------------

SITE = ["export", "latest", "--format", "site", "--out", "x.zip"]


@pytest.mark.parametrize("args, option, accepted", [
    ([*SITE, "--lat", "0", "--lon", "inf", "--radius-km", "0.1"], "--lon", "finite number"),
    ([*SITE, "--lat", "0", "--lon", "nan", "--radius-km", "0.1"], "--lon", "finite number"),
    ([*SITE, "--lat", "0", "--lon", "0", "--radius-km", "inf"], "--radius-km", "> 0 and <= 100"),
    ([*SITE, "--lat", "nan", "--lon", "0", "--radius-km", "0.1"], "--lat", ">= -90 and <= 90"),
    (["images-near", "--lat", "91", "--lon", "0"], "--lat", ">= -90 and <= 90"),
    (["images-near", "--lat", "0", "--lon", "inf"], "--lon", "finite number"),
    (["images-near", "--lat", "0", "--lon", "nan"], "--lon", "finite number"),
    (["images-near", "--lat", "0", "--lon", "0", "--radius-km", "inf"], "--radius-km", "finite number >= 0"),
    (["maplets", "--lat", "0", "--lon", "0", "--radius-km", "nan"], "--radius-km", "finite number >= 0"),
    (["maplets", "--lat", "0", "--lon", "0", "--offset", "99999999999999999999"], "--offset", "2147483647"),
    (["versions", "--limit", "99999999999999999999"], "--limit", "2147483647"),
    (["jobs", "show", "99999999999999999999"], "job_id", "2147483647"),
    (["version", "show", "²"], "version", "version number, release tag, latest or released"),
    (["version", "show", "10^23"], "version", "version number, release tag, latest or released"),
    (["version", "show", "1234567890"], "version", "version number"),
    (["diff", "1", "²"], "new", "version number"),
    (["export", "10^23", "--format", "obj", "--out", "x.obj"], "version", "version number"),
    (["release", "²", "--tag", "v1"], "version", "version number"),
    (["diff", "1", "2", "--threshold-m", "inf"], "--threshold-m", "finite number >= 0"),
    (["simulate", "out", "--psf-px", "nan"], "--psf-px", "finite number"),
    (["simulate", "out", "--start-error", "nan"], "--start-error", "finite and >= 0"),
    (["spg-catalog", "--sigma-position", "inf"], "--sigma-position", "finite number >= 0"),
])
def test_bad_numbers_and_versions_are_usage_errors(pwm, tmp_path, monkeypatch, args, option,
                                                    accepted):
    monkeypatch.chdir(tmp_path)
    result = pwm.invoke(app, args)
    said = _said(result.output).replace("'", "")
    assert result.exit_code == 2, result.output
    assert isinstance(result.exception, SystemExit)  # no traceback
    assert f"Invalid value for {option}" in said and accepted in said, said


def test_directory_commands_check_their_numbers(pwm, tmp_path):
    for args, option in ((["run", str(tmp_path), "--tile-radius-km", "inf"], "--tile-radius-km"),
                         (["watch", str(tmp_path), "--quiet-seconds", "nan"], "--quiet-seconds"),
                         (["refine", str(tmp_path), "--start", str(PWM), "--out", "o",
                           "--search-px", "nan"], "--search-px")):
        result = pwm.invoke(app, args)
        assert result.exit_code == 2 and f"'{option}'" in result.output, (args, result.output)


def test_good_numbers_and_versions_are_taken(pwm, tmp_path):
    # past the parsing: the empty catalog has no version 1
    for args in (["version", "show", "1"], ["version", "show", "nav-2026a"], ["version", "show", "latest"],
                 ["diff", "released", "latest", "--threshold-m", "0"],
                 [*SITE, "--lat", "-90", "--lon", "-360", "--radius-km", "100"]):
        result = pwm.invoke(app, args)
        assert result.exit_code == 1 and "no model version" in result.output, (args, result.output)
    near = pwm.invoke(app, ["images-near", "--lat", "90", "--lon", "359.5", "--radius-km", "1e-3"])
    assert near.exit_code == 0 and near.stdout.endswith("0 images\n"), near.output


# -- settings ---------------------------------------------------------------------------------

BAD_SETTINGS = [
    ("PWM_REFINE_PASSES", "abc", "valid integer"),
    ("PWM_CORS_ORIGINS", "notjson", "JSON list of origins"),
    ("PWM_EXPORT_CACHE_BYTES", "2GB", "valid integer"),
    ("PWM_REFINE_MODE", "fast", "'pwm' or 'standard'"),
    ("PWM_DATABASE_URL", "mysql://operator:hunter2@db/pwm", "sqlite:///FILE or postgresql://"),
    ("PWM_TILE_RADIUS_KM", "inf", "finite number"),
    ("PWM_REFINE_PASSES", "0", "at least one pass"),
]


@pytest.mark.parametrize("variable, value, accepted", BAD_SETTINGS,
                         ids=[f"{v}={x}" for v, x, _ in BAD_SETTINGS])
@pytest.mark.parametrize("command", [["versions"], ["jobs", "list"], ["run", "{tmp}"], ["import", "{model}"]])
def test_a_bad_setting_is_one_line_naming_its_variable(pwm, tmp_path, monkeypatch, variable, value,
                                                       accepted, command):
    model = tmp_path / "model.obj"
    write_obj(model, _sphere())
    monkeypatch.setenv(variable, value)
    result = pwm.invoke(app, [arg.format(tmp=tmp_path, model=model) for arg in command])
    assert result.exit_code == 2, result.output
    assert isinstance(result.exception, SystemExit)
    [line] = result.stderr.splitlines()
    assert line.startswith(f"error: {variable}") and accepted in line, line
    assert "hunter2" not in result.output  # a URL's password is never repeated


def test_every_bad_setting_is_named_at_once(pwm, monkeypatch):
    monkeypatch.setenv("PWM_REFINE_PASSES", "abc")
    monkeypatch.setenv("PWM_REFINE_MODE", "fast")
    result = pwm.invoke(app, ["versions"])
    assert result.exit_code == 2
    assert sorted(line.split("=")[0] for line in result.stderr.splitlines()) == [
        "error: PWM_REFINE_MODE", "error: PWM_REFINE_PASSES"]


def test_the_installed_command_reports_a_bad_setting_in_one_line(tmp_path):
    environment = {"PATH": "/usr/bin:/bin", "PWM_DATA_DIR": str(tmp_path), "PWM_REFINE_PASSES": "abc"}
    done = subprocess.run([str(PWM), "versions"], env=environment, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == ["error: PWM_REFINE_PASSES='abc': Input should be a valid "
                                        "integer, unable to parse string as an integer"]


# -- pwm run ----------------------------------------------------------------------------------

def test_run_exits_with_the_number_of_failed_files(pwm, tmp_path):
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "a.xml").write_text("not xml <")
    (junk / "b.fits").write_bytes(b"\x00" * 4000)
    result = pwm.invoke(app, ["run", str(junk)])
    assert result.exit_code == 2, result.output
    assert result.stderr.count("rejected ") == 2 and "no model to refine" in result.stdout
    empty = tmp_path / "empty"
    empty.mkdir()
    assert pwm.invoke(app, ["run", str(empty)]).exit_code == 0  # nothing failed


# -- pwm import -------------------------------------------------------------------------------

def test_shape_models_are_told_by_their_content(tmp_path):
    mesh = _sphere()
    grid = mesh_to_icq(mesh, 6)
    written = {"obj": write_obj, "ply": write_ply,
               "icq": lambda path, m: write_icq(path, grid),
               "dsk": lambda path, m: write_dsk(path, m, body=499, frame="IAU_MARS", comment="test")}
    for name, write in written.items():
        for suffix in (f".{name}", ".model"):
            path = tmp_path / f"{name}{suffix}"
            write(path, mesh)
            back = read_shape_model(path)
            expected = icq_to_mesh(read_icq(path)) if name == "icq" else mesh
            np.testing.assert_allclose(back.vertices, expected.vertices, atol=1e-6, err_msg=str(path))
            np.testing.assert_array_equal(back.faces, expected.faces)
    assert len(read_shape_model(tmp_path / "icq.model").faces) == 12 * 6**2


def test_damaged_shape_models_are_value_errors(tmp_path):
    dsk = tmp_path / "whole.dsk"
    write_dsk(dsk, _sphere(), body=499, frame="IAU_MARS", comment="test")
    cut = tmp_path / "cut.dsk"
    cut.write_bytes(dsk.read_bytes()[:2048])
    (tmp_path / "short.icq").write_text("4\n1.0 2.0 3.0\n")
    (tmp_path / "junk.bin").write_bytes(bytes(range(256)) * 8)
    for name, reason in (("cut.dsk", "not a readable DSK file"), ("short.icq", "q = 4 needs 150"),
                         ("junk.bin", "no vertices or faces")):
        with pytest.raises(ValueError, match=reason):
            read_shape_model(tmp_path / name)


def test_import_reads_every_format_export_writes(pwm, tmp_path):
    start = tmp_path / "start.obj"
    write_obj(start, _sphere())
    assert pwm.invoke(app, ["import", str(start)]).exit_code == 0
    for number, (fmt, name, extra) in enumerate((("obj", "x.obj", []), ("ply", "x.ply", []),
                                                 ("icq", "x.icq", ["--faces", "300"]),
                                                 ("dsk", "x.dsk", ["--frame", "IAU_MARS"]),
                                                 ("dsk", "dsk-without-suffix", ["--frame", "IAU_MARS"])),
                                                2):
        out = tmp_path / name
        exported = pwm.invoke(app, ["export", "1", "--format", fmt, "--out", str(out), *extra])
        assert exported.exit_code == 0, exported.output
        imported = pwm.invoke(app, ["import", str(out)])
        assert imported.exit_code == 0, (fmt, imported.output)
        assert imported.stdout.startswith(f"version {number} (imported)")
    icq = pwm.invoke(app, ["version", "show", "4"])
    assert '"faces": 300' in icq.stdout  # q = 5: 12 q^2 faces


def test_a_file_that_is_no_shape_model_is_an_error_not_a_traceback(pwm, tmp_path):
    junk = tmp_path / "junk.dsk"
    junk.write_bytes(b"DAS/DSK " + bytes(2000))
    result = pwm.invoke(app, ["import", str(junk)])
    assert result.exit_code == 1 and isinstance(result.exception, SystemExit), result.output
    [line] = result.stderr.splitlines()
    assert line.startswith("error: ") and "not a readable DSK file" in line


def _scratch(data_dir: Path) -> list[Path]:
    """What the data directory's scratch folders hold."""
    return [p for p in data_dir.rglob("*") if p.is_file() and "tmp" in p.relative_to(data_dir).parts]


def test_a_failed_import_write_leaves_no_scratch_file(pwm, tmp_path, monkeypatch):
    import service.versions

    def disk_fills(path, mesh) -> None:
        Path(path).write_text("v 0 0 0\n")  # part of the file, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device")

    model = tmp_path / "model.ply"
    write_ply(model, _sphere())
    monkeypatch.setattr(service.versions, "write_obj", disk_fills)
    result = pwm.invoke(app, ["import", str(model)])
    assert result.exit_code == 1 and "No space left on device" in result.stderr, result.output
    assert _scratch(tmp_path / "data") == []
    assert pwm.invoke(app, ["versions", "--json"]).stdout.strip() == "[]"


def test_a_failed_export_write_leaves_nothing_behind(pwm, tmp_path, monkeypatch):
    import service.cli.exports

    model = tmp_path / "model.obj"
    write_obj(model, _sphere())
    assert pwm.invoke(app, ["import", str(model)]).exit_code == 0

    def disk_fills(source, target) -> None:
        Path(target).write_bytes(Path(source).read_bytes()[:100])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(service.cli.exports.shutil, "copyfile", disk_fills)
    out = tmp_path / "exports" / "model.ply"
    result = pwm.invoke(app, ["export", "1", "--format", "ply", "--out", str(out)])
    assert result.exit_code == 1 and "No space left on device" in result.stderr, result.output
    assert list(out.parent.iterdir()) == []


@pytest.mark.parametrize("command", ["ingest", "run"])
def test_an_ingest_taken_over_ends_in_one_line_not_a_traceback(pwm, tmp_path, monkeypatch,
                                                               command) -> None:
    import service.ingest

    def taken_over(*_args, **_kwargs):
        raise service.ingest.IngestTakenOver("downlink 1 was taken over by the ingest of h:2")

    monkeypatch.setattr(service.ingest, "ingest_directory", taken_over)
    monkeypatch.setattr("service.conductor.ingest_directory", taken_over)
    (tmp_path / "dl").mkdir()
    result = pwm.invoke(app, [command, str(tmp_path / "dl")])
    assert result.exit_code == 1
    assert "taken over by the ingest of h:2" in result.output
    assert "Traceback" not in result.output

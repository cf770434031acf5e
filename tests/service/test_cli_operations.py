"""What operators see of `pwm`: a header on every table, progress as a bounded number of plain
lines where stderr is no terminal, and a first run without the migrations' log."""

from __future__ import annotations

import io
import logging
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from service.cli import app
from service.cli.progress import PLAIN_EVERY_S, PlainProgress, progress_bar
from service.db import upgrade

PWM = Path(sys.executable).with_name("pwm")


@pytest.mark.parametrize("args, columns", [
    (["images"], ["LIDVID", "status", "start (UTC)", "range km", "inc", "emi", "pha"]),
    (["images-near", "--lat", "0", "--lon", "0"], ["LIDVID", "start (UTC)", "maplet", "weight", "m/px", "role"]),
    (["maplets"], ["maplet", "lat", "lon", "size m", "gsd m", "level", "rev", "images"]),
    (["versions"], ["version", "kind", "parent", "created (UTC)", "faces", "downlinks"]),
    (["jobs", "list"], ["id", "kind", "status", "attempts", "progress", "worker", "heartbeat", "key"]),
    (["kernels"], ["id", "kind", "file", "status", "coverage (UTC)", "downlinks"]),
    (["downlinks"], ["id", "downlink", "status", "outcome", "accepted", "rejected"]),
])
def test_every_table_has_a_header(pwm, args, columns):
    result = pwm.invoke(app, args)
    assert result.exit_code == 0, result.output
    header = result.stdout.splitlines()[0]
    assert all(column in header for column in columns), header


def test_progress_off_a_terminal_is_a_few_plain_lines():
    stream, clock = io.StringIO(), [0.0]
    progress = PlainProgress(stream, unit="maplets", now=lambda: clock[0])
    for done in range(1001):  # a thousand maplets, a second each
        progress("refine round 1", done, 1000)
        clock[0] += 1.0
    lines = stream.getvalue().splitlines()
    # a line per tenth (0 % to 100 %), and one at least every PLAIN_EVERY_S between them
    assert 11 <= len(lines) <= 11 + 1000 / PLAIN_EVERY_S
    assert lines[0].startswith("refine round 1: 0/1000 maplets (0%)")
    assert lines[-1].startswith("refine round 1: 1000/1000 maplets (100%), 0:16:40 elapsed")
    assert "about 0:15:00 left" in next(line for line in lines if "100/1000" in line)
    assert "\x1b" not in stream.getvalue()
    progress("refine round 2", 0, 0)  # nothing to refine: nothing said
    assert len(stream.getvalue().splitlines()) == len(lines)


def test_progress_bar_prints_no_control_codes_into_a_pipe():
    stream = io.StringIO()
    with progress_bar(stream=stream) as progress:
        for done in range(5):
            progress("refine", done, 4)
    assert "\x1b" not in stream.getvalue() and "\r" not in stream.getvalue()
    assert stream.getvalue().splitlines()[-1].startswith("refine: 4/4 maplets (100%)")


def test_a_first_run_says_the_catalog_was_created_and_nothing_of_the_migrations(tmp_path, caplog):
    environment = {k: v for k, v in os.environ.items() if not k.startswith("PWM_")}
    environment |= {"PWM_DATA_DIR": str(tmp_path / "data"), "COLUMNS": "200"}
    (tmp_path / "empty").mkdir()
    result = subprocess.run([str(PWM), "run", str(tmp_path / "empty")], env=environment, capture_output=True,
                            text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    assert "alembic" not in result.stderr.lower() and "Running upgrade" not in result.stderr
    [created] = [line for line in result.stderr.splitlines() if "catalog" in line and "revision" in line]
    assert created.split(" ", 1)[1].startswith("INFO catalog created at revision ")
    # a catalog at the latest revision already: not a line
    with caplog.at_level(logging.INFO):
        upgrade(f"sqlite:///{tmp_path / 'data' / 'catalog.sqlite'}")
    assert not [r for r in caplog.records if r.levelno >= logging.INFO], caplog.records


def _commands(group, path=()):
    """Every command's path under the click group, the group's own first."""
    yield path
    for name, command in getattr(group, "commands", {}).items():
        yield from _commands(command, (*path, name))


def _broken(lines: list[str], width: int) -> list[str]:
    """The lines of wrapped paragraphs that end where the next line's first word would have fit."""
    return [line for line, after in zip(lines, lines[1:], strict=False)
            if line.strip() and after.strip() and len(line.rstrip()) + 1 + len(after.split()[0]) <= width]


def test_help_never_breaks_a_sentence_mid_line(pwm, monkeypatch):
    import typer.main

    monkeypatch.setenv("COLUMNS", "100")
    for path in _commands(typer.main.get_command(app)):
        shown = pwm.invoke(app, [*path, "--help"]).stdout.splitlines()
        # the description: from the usage line to the first panel, paragraphs apart
        text = shown[shown.index(next(s for s in shown if "Usage:" in s)) + 1:]
        text = text[:next((k for k, s in enumerate(text) if s.startswith("╭")), len(text))]
        assert not _broken(text, 99), (path, text)
        # the commands panel: each command's summary in its column
        if not any(s.startswith("╭─ Commands") for s in shown):
            continue
        panel = shown[next(k for k, s in enumerate(shown) if s.startswith("╭─ Commands")) + 1:]
        rows = [s[2:-2] for s in panel[:next(k for k, s in enumerate(panel) if s.startswith("╰"))]]
        start = re.match(r"\S+\s+", rows[0]).end()
        summaries: list[list[str]] = []
        for row in rows:
            if row[:start].strip():  # a command's name: its summary starts
                summaries.append([])
            summaries[-1].append(row[start:])
        for summary in summaries:
            assert not _broken(summary, len(rows[0]) - start), (path, summary)

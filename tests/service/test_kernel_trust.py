"""Kernels are checked before they are trusted (issue 44): binary kernels read through, text
kernels' body and time constants checked and kept from changing catalogued geometry, kernel rows
inserted race-free by concurrent ingests, and an operator retiring a kernel with `pwm kernels`."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import spiceypy as sp
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker
from typer.testing import CliRunner

from pwm.io.dsk import write_dsk
from pwm.io.kernel_checks import check_das
from pwm.io.meshio import read_obj
from pwm.io.spice_kernels import bundled_kernels, kernel_pool
from service.cli import app
from service.db import make_engine, make_sessionmaker, upgrade
from service.ingest import ingest_directory
from service.rows import (
    Acceptance,
    GeometryStatus,
    Image,
    ImageGeometry,
    ImageStatus,
    Kernel,
    KernelCoverage,
    KernelDelivery,
)
from service.settings import get_settings
from tests.service import test_ingest as base

# The synthetic MapCam kernels and downlink of test_ingest (three good products, kernels inside).
kernels = base.kernels
downlink = base.downlink
REPO = Path(__file__).resolve().parents[2]
BENNU_RADII = "BODY2101955_RADII"


def _geometry(catalog: sessionmaker[Session]) -> dict[str, tuple]:
    """Each image's stored geometry by LIDVID (None where it has none)."""
    with catalog() as session:
        rows = session.execute(
            select(Image.lidvid, Image.geometry_status, ImageGeometry.camera_x_km,
                   ImageGeometry.camera_y_km, ImageGeometry.camera_z_km,
                   ImageGeometry.camera_rotation, ImageGeometry.intercept_lat_deg,
                   ImageGeometry.intercept_lon_deg, ImageGeometry.computed_at)
            .outerjoin(ImageGeometry))
        return {lidvid: tuple(rest) for lidvid, *rest in rows}


def _kernels(catalog: sessionmaker[Session]) -> dict[str, Kernel]:
    with catalog() as session:
        return {Path(k.path).name: k for k in session.scalars(select(Kernel))}


def _image(catalog: sessionmaker[Session], name: str) -> Image:
    with catalog() as session:
        return session.scalars(select(Image).where(Image.lid.endswith(f":{name}"))).one()


def _with_geometry(image: Image) -> None:
    assert (image.status, image.geometry_status) == (ImageStatus.ACCEPTED,
                                                     GeometryStatus.COMPUTED), (
        image.rejection_code, image.rejection_reason, image.geometry_unavailable_reason)


def _truncated(source: Path, target: Path) -> Path:
    """`source` less its last 1024-byte record: its summaries kept, its data cut short."""
    target.write_bytes(source.read_bytes()[:-1024])
    return target


def _text_kernel(source: Path, target: Path, variable: str, value: str) -> Path:
    """`source`, a text kernel, with `variable`'s assignment replaced by `value`."""
    text = source.read_text()
    start = text.index(variable)
    end = text.index(")", start) + 1
    target.write_text(text[:start] + f"{variable} = {value}" + text[end:])
    return target


def _bad_kernels(directory: Path, kernels: dict) -> dict[str, str]:
    """The hostile kernels of a later downlink, by file name, with the code each must get."""
    directory.mkdir(parents=True)
    files = {f.name: f for f in kernels["files"]}
    pck, lsk = bundled_kernels()["bennu_v16.tpc"], bundled_kernels()["naif0012.tls"]
    with kernel_pool([pck]):
        radii = sp.bodvrd("BENNU", "RADII", 3)[1]
    _truncated(files["orx_sc.bsp"], directory / "orx_sc_cut.bsp")
    _truncated(files["orx_sc.bc"], directory / "orx_sc_cut.bc")
    _text_kernel(pck, directory / "bennu_strings.tpc", BENNU_RADII, "( 'a' 'b' 'c' )")
    _text_kernel(pck, directory / "bennu_zero.tpc", BENNU_RADII, "( 0 0 0 )")
    _text_kernel(pck, directory / "bennu_big.tpc", BENNU_RADII,
                 "( " + " ".join(f"{2 * r:.6f}" for r in radii) + " )")
    _text_kernel(lsk, directory / "naif_shifted.tls", "DELTET/DELTA_T_A", "( 3632.184 )")
    return {"orx_sc_cut.bsp": "kernel_truncated", "orx_sc_cut.bc": "kernel_truncated",
            "bennu_strings.tpc": "kernel_constants", "bennu_zero.tpc": "kernel_constants",
            "bennu_big.tpc": "kernel_redefines", "naif_shifted.tls": "kernel_constants"}


def test_bad_kernels_of_a_later_downlink_are_rejected_and_change_no_geometry(
    catalog: sessionmaker[Session], downlink: Path, kernels: dict, tmp_path: Path
) -> None:
    """A truncated SPK and CK, PCKs with string, zero or other radii and an LSK moving
    DELTA_T_A by an hour, in a later downlink with a good image of its own: each is rejected
    with why, the first downlink's geometry stays as it was, and the later downlink's image and
    a third downlink's get geometry."""
    first = ingest_directory(catalog, downlink)
    assert first.failed == 0, first.failures
    before = _geometry(catalog)
    assert len(before) == 3 and all(g[0] == GeometryStatus.COMPUTED for g in before.values())

    later = tmp_path / "later"
    expected = _bad_kernels(later / "kernels", kernels)
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        base._product(later / "images", "later0", kernels["et0"] + 300.0)
    report = ingest_directory(catalog, later)

    assert {Path(f.path).name: f.code for f in report.failures} == expected
    rows = _kernels(catalog)
    for name, code in expected.items():
        assert (rows[name].status, rows[name].rejection_code) == (Acceptance.REJECTED, code)
    assert "not within the file's" in rows["orx_sc_cut.bsp"].rejection_reason
    assert "numbers are due, not strings" in rows["bennu_strings.tpc"].rejection_reason
    assert "three positive numbers" in rows["bennu_zero.tpc"].rejection_reason
    assert "DELTET/DELTA_T_A = ( 3632.184 )" in rows["naif_shifted.tls"].rejection_reason
    big = rows["bennu_big.tpc"].rejection_reason
    assert f"{BENNU_RADII} = ( 0.56613 0.54243 0.49944 ) (was ( 0.283065 0.271215 0.24972 ))" in big

    assert {k: v for k, v in _geometry(catalog).items() if k in before} == before
    _with_geometry(_image(catalog, "later0"))

    again = ingest_directory(catalog, later)  # still rejected, no news
    assert again.failed == 0 and again.kernels.unchanged == len(expected)

    third = tmp_path / "third"
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        base._product(third / "images", "third0", kernels["et0"] + 1860.0)
    ingest_directory(catalog, third)
    _with_geometry(_image(catalog, "third0"))
    good = _image(catalog, "good0")
    with catalog() as session:
        ranges = {lidvid: r for lidvid, r in session.execute(
            select(Image.lidvid, ImageGeometry.intercept_range_km).join(ImageGeometry))}
    assert ranges[_image(catalog, "third0").lidvid] == pytest.approx(ranges[good.lidvid], rel=0.1)


def test_the_same_constants_again_and_a_longer_leap_second_table_are_accepted(
    sqlite_url: str, open_catalog_at, downlink: Path, tmp_path: Path
) -> None:
    """A PCK giving Bennu's radii as the catalogued ones (written another way) and an LSK
    adding a leap second after the catalogued ones redefine nothing."""
    catalog = open_catalog_at(sqlite_url)
    ingest_directory(catalog, downlink)
    later = tmp_path / "later" / "kernels"
    later.mkdir(parents=True)
    pck, lsk = bundled_kernels()["bennu_v16.tpc"], bundled_kernels()["naif0012.tls"]
    with kernel_pool([pck]):
        radii = sp.bodvrd("BENNU", "RADII", 3)[1]
    _text_kernel(pck, later / "bennu_again.tpc", BENNU_RADII,
                 "( " + " ".join(f"{r * 1000:.3f}D-3" for r in radii) + " )")
    text = lsk.read_text()
    last = "@2017-JAN-1"
    assert f"{last} )" in text  # naif0012's last leap second
    (later / "naif_next.tls").write_text(text.replace(f"{last} )", f"{last}\n 38, @2030-JAN-1 )"))
    report = ingest_directory(catalog, later.parent)
    assert report.failed == 0, report.failures
    rows = _kernels(catalog)
    assert rows["bennu_again.tpc"].status == rows["naif_next.tls"].status == Acceptance.ACCEPTED


def test_a_truncated_dsk_is_refused(sqlite_url: str, open_catalog_at, downlink: Path) -> None:
    """A DSK less its last record, whose summaries SPICE still reads, is rejected; the whole
    one is accepted."""
    mesh = read_obj(base.BUNDLED_SHAPE)
    whole = downlink / "kernels" / "bennu.bds"
    write_dsk(whole, mesh, body=2101955, frame="IAU_BENNU", comment="test")
    cut = _truncated(whole, downlink / "kernels" / "bennu_cut.bds")
    assert list(sp.dskobj(str(cut))) == [2101955]  # SPICE's summary reader takes it
    report = ingest_directory(open_catalog_at(sqlite_url), downlink)
    assert [(Path(f.path).name, f.code) for f in report.failures] == [
        ("bennu_cut.bds", "kernel_truncated")]
    assert "past the file's" in report.failures[0].reason
    assert check_das(whole) == 1


# ---------------------------------------------------------------------------------------------
# Two ingests registering the same kernels at once

_REGISTER = """
import json, sys, time
from pathlib import Path
from service.db import make_engine, make_sessionmaker, session_scope
from service.kernels import KernelScope, register_kernels
from service.rows import Downlink
url, directory, name, sync = sys.argv[1:]
sessions = make_sessionmaker(make_engine(url))
with session_scope(sessions) as session:
    row = Downlink(name=name, path=directory)
    session.add(row)
    session.flush()
    downlink_id = row.id
Path(sync, name).touch()
while not Path(sync, "go").exists():
    time.sleep(0.005)
with session_scope(sessions) as session:
    outcomes = register_kernels(session, KernelScope(Path(directory)), downlink_id=downlink_id)
    time.sleep(2.0)  # the other has read the catalog before this one commits
print(json.dumps([[str(o.path), o.result, o.code, o.reason] for o in outcomes]))
"""


def test_two_ingests_registering_the_same_kernels_at_once(db_url: str, kernels: dict,
                                                          tmp_path: Path) -> None:
    """Two processes register the same new kernels from two downlinks at the same moment: one
    inserts each row, the other takes it; nothing is rejected, no row or window is doubled,
    and each kernel lists both deliveries."""
    upgrade(db_url)
    sync = tmp_path / "sync"
    sync.mkdir()
    names = ("first", "second")
    for name in names:
        (tmp_path / name).mkdir()
        for f in kernels["files"]:
            shutil.copy(f, tmp_path / name / f.name)
    processes = [subprocess.Popen([sys.executable, "-c", _REGISTER, db_url, str(tmp_path / n), n,
                                   str(sync)], cwd=REPO, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True) for n in names]
    deadline = time.monotonic() + 120
    while not all((sync / n).exists() for n in names) and time.monotonic() < deadline:
        assert all(p.poll() is None for p in processes), [p.communicate() for p in processes]
        time.sleep(0.01)
    (sync / "go").touch()
    results = [p.communicate(timeout=180) for p in processes]
    assert [p.returncode for p in processes] == [0, 0], [err for _, err in results]
    by_kernel: dict[str, list[str]] = {}
    for out, _ in results:
        for path, result, _, _ in json.loads(out):
            by_kernel.setdefault(Path(path).name, []).append(result)
    n = len(kernels["files"])
    # each kernel inserted by one, taken by the other (which one may differ kernel by kernel)
    assert {name: sorted(r) for name, r in by_kernel.items()} == {
        f.name: ["accepted", "unchanged"] for f in kernels["files"]}

    engine = make_engine(db_url)
    try:
        with make_sessionmaker(engine)() as session:
            rows = list(session.scalars(select(Kernel)))
            windows = session.scalar(select(func.count()).select_from(KernelCoverage))
            deliveries = session.scalar(select(func.count()).select_from(KernelDelivery))
    finally:
        engine.dispose()
    assert len(rows) == n and all(k.status == Acceptance.ACCEPTED for k in rows)
    assert windows == 6  # orx_sc.bsp 1, bennu_sun.bsp 2, orx_sc.bc 2 windows, struct CK 1
    assert deliveries == 2 * n


# ---------------------------------------------------------------------------------------------
# `pwm kernels` and retiring a kernel


def _cli(db_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, *args: str):
    monkeypatch.setenv("PWM_DATABASE_URL", db_url)
    monkeypatch.setenv("PWM_DATA_DIR", str(tmp_path / "data"))
    get_settings.cache_clear()
    try:
        return CliRunner().invoke(app, list(args))
    finally:
        get_settings.cache_clear()


def test_a_retired_kernel_withdraws_the_geometry_it_served_for_good(
    db_url: str, open_catalog_at, downlink: Path, kernels: dict, tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch
) -> None:
    """`pwm kernels retire` the spacecraft's SPK: the images it served lose their geometry with
    a reason naming the retirement; ingesting the downlink again, the SPK still in it, neither
    brings the kernel back nor gives them geometry. `pwm kernels` lists it retired."""
    catalog = open_catalog_at(db_url)
    ingest_directory(catalog, downlink)
    spk = _kernels(catalog)["orx_sc.bsp"]

    listed = _cli(db_url, tmp_path, monkeypatch, "kernels", "--json")
    assert listed.exit_code == 0, listed.output
    entry = next(k for k in json.loads(listed.output) if k["id"] == spk.id)
    assert (entry["kind"], entry["status"], entry["downlinks"]) == ("spk", "accepted", ["downlink"])
    assert entry["coverage"]["start_utc"].startswith("2019-03-03T10:00:00")

    retired = _cli(db_url, tmp_path, monkeypatch, "kernels", "retire", str(spk.id),
                   "--reason", "navigation team: bad solution")
    assert retired.exit_code == 0, retired.output
    assert "3 images lost their geometry" in retired.output
    assert f"pwm run {downlink.resolve()}" in retired.output
    for k in range(3):
        image = _image(catalog, f"good{k}")
        assert (image.status, image.geometry_status) == (ImageStatus.ACCEPTED,
                                                         GeometryStatus.UNAVAILABLE)
        assert image.geometry_unavailable_reason == (
            f"kernel {spk.id} (orx_sc.bsp) retired: navigation team: bad solution")
        assert image.coverage_computed_at is None
    assert all(g[1] is None for g in _geometry(catalog).values())

    again = ingest_directory(catalog, downlink)
    assert again.kernels.accepted == 0
    assert _kernels(catalog)["orx_sc.bsp"].retired_at is not None
    assert all(g[0] != GeometryStatus.COMPUTED and g[1] is None
               for g in _geometry(catalog).values())
    table = _cli(db_url, tmp_path, monkeypatch, "kernels")
    line = next(x for x in table.output.splitlines() if "orx_sc.bsp" in x)
    assert "retired" in line
    assert "navigation team: bad solution" in table.output
    missing = _cli(db_url, tmp_path, monkeypatch, "kernels", "retire", "9999")
    assert missing.exit_code == 1 and "no kernel 9999" in missing.output


def test_retiring_a_pck_lets_a_new_one_change_the_radii(
    sqlite_url: str, open_catalog_at, downlink: Path, tmp_path: Path
) -> None:
    """A PCK changing Bennu's radii is refused while the catalogued one is in use; once that one
    is retired, every image's geometry is withdrawn and the new PCK, delivered again, is
    accepted, and the images get their geometry from it at their downlink's next ingest."""
    from service.db import session_scope
    from service.kernels import retire_kernel

    catalog = open_catalog_at(sqlite_url)
    ingest_directory(catalog, downlink)
    before = _intercept_range_km(catalog, "good0")
    later = tmp_path / "later" / "kernels"
    later.mkdir(parents=True)
    pck = bundled_kernels()["bennu_v16.tpc"]
    with kernel_pool([pck]):
        radii = sp.bodvrd("BENNU", "RADII", 3)[1]
    _text_kernel(pck, later / "bennu_v17.tpc", BENNU_RADII,
                 "( " + " ".join(f"{1.01 * r:.6f}" for r in radii) + " )")
    refused = ingest_directory(catalog, later.parent)
    assert [f.code for f in refused.failures] == ["kernel_redefines"]
    with session_scope(catalog) as session:
        done = retire_kernel(session, _kernels(catalog)["bennu_v16.tpc"].id, reason="v17")
    assert done.images == 3
    assert ingest_directory(catalog, later.parent).kernels.accepted == 1
    ingest_directory(catalog, downlink)
    _with_geometry(_image(catalog, "good0"))
    # Bennu 1 % larger: the boresight meets it about 1 % of its radius nearer
    assert before - _intercept_range_km(catalog, "good0") == pytest.approx(0.0027, abs=0.001)


def _intercept_range_km(catalog: sessionmaker[Session], name: str) -> float:
    with catalog() as session:
        return session.scalars(select(ImageGeometry.intercept_range_km).join(Image)
                               .where(Image.lid.endswith(f":{name}"))).one()

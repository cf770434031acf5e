"""A product's identity is its good content (issue 44): a copy rejected for how it arrived
(missing, cut short, a checksum off its label or the downlink's manifest) never keeps a later
whole copy of the same LIDVID out; unique rows are inserted race-free by concurrent ingests; and
a label's file references are counted before any is read."""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from pwm.io.spice_kernels import bundled_kernels, kernel_pool
from service import ingest
from service.db import make_engine, make_sessionmaker
from service.ingest import ingest_directory
from service.rows import Downlink, DownlinkStatus, GeometryStatus, Image, ImageStatus
from service.settings import IngestLimits
from tests.service import test_ingest as base

# The synthetic MapCam kernels and downlink of test_ingest (three good products, kernels inside).
kernels = base.kernels
downlink = base.downlink
CK_OFFSETS_S = [60.0, 150.0, 300.0, 450.0, 1830.0, 2100.0]  # inside the CK windows


def _copies(catalog: sessionmaker[Session], lid_suffix: str) -> list[Image]:
    """The rows of the product whose LID ends with `lid_suffix`, oldest first."""
    with catalog() as session:
        return list(session.scalars(select(Image).where(Image.lid.endswith(f":{lid_suffix}"))
                                    .order_by(Image.id)))


def _manifest(directory: Path) -> None:
    """A manifest.json listing every file of `directory` with its size and sha256, as `pwm
    simulate` writes it."""
    entries = [{"path": p.relative_to(directory).as_posix(), "bytes": p.stat().st_size,
                "sha256": hashlib.sha256(p.read_bytes()).hexdigest()}
               for p in sorted(directory.rglob("*")) if p.is_file()]
    (directory / "manifest.json").write_text(json.dumps({"files": entries}))


def _flip(path: Path) -> bytes:
    """Flip one byte inside the array (after the 2880-byte FITS header); the whole content."""
    whole = path.read_bytes()
    broken = bytearray(whole)
    broken[3000] ^= 0x01
    path.write_bytes(bytes(broken))
    return whole


def _accepted_with_geometry(image: Image) -> None:
    assert (image.status, image.geometry_status) == (ImageStatus.ACCEPTED, GeometryStatus.COMPUTED), (
        image.rejection_code, image.rejection_reason, image.geometry_unavailable_reason)


def test_the_issues_reproduction_a_label_before_its_data_file(catalog, tiny_sim, tmp_path) -> None:
    """Move images/pwm_tiny_img000.fits away, ingest, move it back, ingest: the product is
    accepted with geometry on its first row (its id kept), and no conflict is left."""
    root = tmp_path / "downlink"
    shutil.copytree(tiny_sim / "downlink", root)
    data = root / "images" / "pwm_tiny_img000.fits"
    data.rename(tmp_path / data.name)
    first = ingest_directory(catalog, root)
    assert [(Path(f.path).name, f.code) for f in first.failures] == [("pwm_tiny_img000.xml", "missing_file")]
    [waiting] = _copies(catalog, "pwm_tiny_img000")
    assert (waiting.status, waiting.rejection_code) == (ImageStatus.REJECTED, "missing_file")

    (tmp_path / data.name).rename(data)
    second = ingest_directory(catalog, root)
    assert (second.images.accepted, second.failed) == (1, 0), second.failures
    [image] = _copies(catalog, "pwm_tiny_img000")
    _accepted_with_geometry(image)
    assert image.id == waiting.id and image.lidvid == waiting.lidvid
    assert ingest_directory(catalog, root).images.unchanged == 6


def test_a_truncated_transfer_then_the_whole_file_is_accepted(catalog, downlink, kernels) -> None:
    _, data = base._bad_product(downlink, kernels)
    whole = data.read_bytes()
    data.write_bytes(whole[:-500])
    ingest_directory(catalog, downlink)
    [cut] = _copies(catalog, "bad")
    assert (cut.status, cut.rejection_code) == (ImageStatus.REJECTED, "size_mismatch")

    data.write_bytes(whole)
    report = ingest_directory(catalog, downlink)
    assert (report.images.accepted, report.images.unchanged, report.failed) == (1, 3, 0)
    [image] = _copies(catalog, "bad")
    _accepted_with_geometry(image)
    assert image.id == cut.id


@pytest.mark.parametrize("first_kept", [True, False])
def test_a_broken_copy_in_one_downlink_then_a_whole_one_in_another(catalog, downlink, kernels,
                                                                   tmp_path, first_kept) -> None:
    """The whole copy takes the product's row (its id kept) for its own downlink; the broken
    copy the first downlink offered, while it is still there, is kept as a copy not used, with
    why (a partial delivery removed before the whole one came leaves nothing behind)."""
    label, data = base._bad_product(downlink, kernels)
    resent = tmp_path / "resent"
    (resent / "images").mkdir(parents=True)
    shutil.copy(label, resent / "images")
    shutil.copy(data, resent / "images")
    _flip(data)
    ingest_directory(catalog, downlink)
    [broken] = _copies(catalog, "bad")
    assert broken.rejection_code == "md5_mismatch"
    if not first_kept:
        label.unlink()
        data.unlink()

    report = ingest_directory(catalog, resent)
    assert (report.images.accepted, report.failed) == (1, 0), report.failures
    image, *unused = _copies(catalog, "bad")
    _accepted_with_geometry(image)
    assert image.id == broken.id and image.lidvid == broken.lidvid
    assert image.label_path == str(resent / "images" / label.name) and image.downlink_id != broken.downlink_id
    if not first_kept:
        assert unused == []
        return
    [copy] = unused
    assert (copy.status, copy.downlink_id, copy.label_path) == (
        ImageStatus.CONFLICT, broken.downlink_id, str(label))
    assert "md5" in copy.rejection_reason and image.sha256 in copy.rejection_reason
    for again in (downlink, resent):
        assert ingest_directory(catalog, again).failed == 0
    assert [c.status for c in _copies(catalog, "bad")] == [ImageStatus.ACCEPTED, ImageStatus.CONFLICT]


@pytest.mark.parametrize("broken_dir", ["a", "b"])
def test_of_two_copies_in_one_downlink_the_whole_one_wins(catalog, downlink, kernels, broken_dir) -> None:
    """A copy without its data file and a whole copy of one product, in either path order:
    the whole one is the product, the other a copy not used; a re-run changes nothing."""
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        for sub in ("a", "b"):
            base._product(downlink / "images" / sub, "twin", kernels["et0"] + 200.0)
    (downlink / "images" / broken_dir / "twin.fits").unlink()
    report = ingest_directory(catalog, downlink)
    assert report.images.accepted == 4
    image, unused = _copies(catalog, "twin")
    _accepted_with_geometry(image)
    whole_dir = "b" if broken_dir == "a" else "a"
    assert Path(image.label_path).parent.name == whole_dir
    assert (unused.status, Path(unused.label_path).parent.name) == (ImageStatus.CONFLICT, broken_dir)
    again = ingest_directory(catalog, downlink)
    assert (again.images.unchanged, again.failed) == (5, 0)


def test_a_product_off_its_manifest_waits_as_incomplete(catalog, downlink, kernels) -> None:
    """A data file that differs from the manifest's sha256 is a transfer in progress: rejected
    incomplete (the file, both digests), judged again, and accepted once it matches."""
    _, data = base._bad_product(downlink, kernels)
    _manifest(downlink)
    listed = hashlib.sha256(data.read_bytes()).hexdigest()
    whole = _flip(data)
    first = ingest_directory(catalog, downlink)
    assert [f.code for f in first.failures] == ["incomplete"]
    [waiting] = _copies(catalog, "bad")
    assert waiting.rejection_code == "incomplete"
    reason = waiting.rejection_reason
    assert "images/bad.fits" in reason and listed in reason
    assert hashlib.sha256(data.read_bytes()).hexdigest() in reason

    data.write_bytes(whole)
    second = ingest_directory(catalog, downlink)
    assert (second.images.accepted, second.failed) == (1, 0)
    [image] = _copies(catalog, "bad")
    _accepted_with_geometry(image)
    assert image.id == waiting.id


def _second_downlink(root: Path, kernels: dict, names: list[str]) -> Path:
    (root / "kernels").mkdir(parents=True)
    for f in kernels["files"]:
        shutil.copy(f, root / "kernels" / f.name)
    with kernel_pool([bundled_kernels()["naif0012.tls"]]):
        for name, offset in zip(names, CK_OFFSETS_S, strict=True):
            base._product(root / "images", name, kernels["et0"] + offset)
    return root


def _ingest_at(barrier: Any, url: str, directory: Path) -> None:
    """In a process of its own: ingest `directory` once `barrier` lets all parties go; the exit
    status is the number of failed files."""
    sessions = make_sessionmaker(make_engine(url))
    barrier.wait(timeout=120)
    sys.exit(min(ingest_directory(sessions, directory).failed, 100))


def test_two_first_ingests_of_downlinks_sharing_kernels_at_once(catalog, db_url, kernels, tmp_path) -> None:
    """Two processes ingest two new downlinks with the same kernels and camera at the same
    moment (and one product in both): every image is accepted with geometry, nothing is
    rejected unexpectedly, and no LIDVID is doubled."""
    first = _second_downlink(tmp_path / "one", kernels, [f"one{k}" for k in range(6)])
    second = _second_downlink(tmp_path / "two", kernels, [f"two{k}" for k in range(6)])
    shutil.copy(first / "images" / "one0.xml", second / "images")
    shutil.copy(first / "images" / "one0.fits", second / "images")
    spawn = multiprocessing.get_context("spawn")
    barrier = spawn.Barrier(2)
    runs = [spawn.Process(target=_ingest_at, args=(barrier, db_url, d)) for d in (first, second)]
    for run in runs:
        run.start()
    for run in runs:
        run.join(timeout=300)
    assert [run.exitcode for run in runs] == [0, 0]
    with catalog() as session:
        images = session.scalars(select(Image)).all()
    assert sorted(Path(i.label_path).stem for i in images) == sorted(
        [f"one{k}" for k in range(6)] + [f"two{k}" for k in range(6)])
    for image in images:
        _accepted_with_geometry(image)


def test_an_ingest_taken_over_as_stale_stops_writing(catalog, db_url, downlink, monkeypatch) -> None:
    """An ingest paused past the stale limit, its downlink taken over and ingested by another
    process meanwhile, stops when it resumes: it raises, commits nothing more, and leaves no
    rejection of its own (the products it had read are the other's)."""
    original = ingest._identify
    taker: list[tuple[int, str, str]] = []

    def paused(*args: Any) -> Any:
        if not taker:  # the first product: this ingest stalls while another takes over
            run = base._ingest_command(downlink, db_url)
            taker.append((run.wait(timeout=240), *run.communicate()))
        return original(*args)

    monkeypatch.setattr(ingest, "_identify", paused)
    monkeypatch.setenv("PWM_INGEST_STALE_S", "1")  # the other's (a process of its own)
    with pytest.raises(ingest.IngestTakenOver, match="taken over"):
        ingest_directory(catalog, downlink, limits=IngestLimits())
    [(code, out, err)] = taker
    assert code == 0 and "3 accepted" in out, err
    with catalog() as session:
        images = session.scalars(select(Image)).all()
        row = session.scalars(select(Downlink)).one()
    assert len(images) == 3
    for image in images:
        _accepted_with_geometry(image)
    assert (row.status, row.ingest_owner) == (DownlinkStatus.INGESTED, None)


def test_a_label_naming_one_file_ten_thousand_times_is_rejected_fast(catalog, downlink, kernels) -> None:
    """Counted before anything is read: not hashed 10,000 times (2 MiB each), rejected with the
    count and the bound."""
    label, _ = base._bad_product(downlink, kernels)
    (downlink / "images" / "big.bin").write_bytes(b"\0" * (2 << 20))
    extra = "<File_Area_Observational_Supplemental><File><file_name>big.bin</file_name></File>" \
            "</File_Area_Observational_Supplemental>" * 10_000
    text = label.read_text()
    label.write_text(text.replace("</Product_Observational>", extra + "</Product_Observational>"))
    clock = time.perf_counter()
    report = ingest_directory(catalog, downlink, limits=IngestLimits(max_label_files=64))
    assert time.perf_counter() - clock < 10.0
    [failure] = report.failures
    assert failure.code == "too_many_files" and "10001" in failure.reason and "64" in failure.reason
    [image] = _copies(catalog, "bad")
    assert (image.status, image.rejection_code) == (ImageStatus.REJECTED, "too_many_files")


def test_file_references_are_hashed_once_each(catalog, downlink, kernels) -> None:
    """A data file named twice by its label is one file of the product: the product's digest is
    that of the label and the file, once."""
    label, data = base._bad_product(downlink, kernels)
    text = label.read_text()
    label.write_text(text.replace(
        "</Product_Observational>",
        "<File_Area_Observational_Supplemental><File><file_name>bad.fits</file_name></File>"
        "</File_Area_Observational_Supplemental></Product_Observational>"))
    ingest_directory(catalog, downlink)
    [image] = _copies(catalog, "bad")
    assert image.sha256 == hashlib.sha256(label.read_bytes() + data.read_bytes()).hexdigest()

"""The downlink reader (pwm.io.downlink) on a second mission, Hayabusa2's ONC-T at Ryugu: what
each image is comes from its label and the kernels, each camera's images get their own camera,
bad products are skipped with ingest's codes, overrides override."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from pwm.io.downlink import NoUsableImages, read_downlink
from pwm.io.pds4 import read_image_product
from pwm.io.spice_geometry import camera_from_kernel, camera_pose
from pwm.io.spice_kernels import kernel_pool
from service.ingest import ingest_directory
from service.rows import Image, Instrument

ONC_T, ONC_W1 = -37100, -37110
WIDE = ("img001", "img003")  # relabelled as ONC-W1's


def copy_downlink(sim: Path, dest: Path) -> Path:
    """A copy of a simulated downlink (its meta-kernel still names the original's kernels),
    without its manifest: the tests edit its files, which ingest would otherwise take for
    products still arriving (incomplete)."""
    copy = Path(shutil.copytree(sim / "downlink", dest / "downlink"))
    (copy / "manifest.json").unlink()
    return copy


def relabel(downlink: Path, stems: tuple[str, ...], instrument: str) -> None:
    """Make the labels of images *<stem> name another instrument of the same spacecraft."""
    for stem in stems:
        label = next((downlink / "images").glob(f"*_{stem}.xml"))
        text = label.read_text()
        assert text.count("<name>ONC-T</name>") == 1
        label.write_text(text.replace("<name>ONC-T</name>", f"<name>{instrument}</name>"))


def add_bad_products(downlink: Path, shared_data: Path) -> dict[str, str]:
    """A truncated data file, a real Hayabusa2 TIR product (no TIR camera in the kernels) and a
    label that is not XML; returns the label names with the code each is skipped with."""
    images = downlink / "images"
    data = next(images.glob("*_img005.fits"))
    data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])
    for f in (shared_data / "pds4" / "hyb2_tir").iterdir():
        shutil.copyfile(f, images / f.name)
    (images / "broken.xml").write_text("<Product_Observational><not closed")
    return {f"{data.stem}.xml": "size_mismatch", "hyb2_tir_20180629_075501_l1.xml": "unknown_instrument",
            "broken.xml": "malformed_xml"}


def test_the_labels_and_kernels_say_what_each_image_is(ryugu_sim):
    read = read_downlink(ryugu_sim / "downlink")
    assert len(read.views) == 6 and read.skipped == []
    assert read.body_frame == "RYUGU_FIXED" and read.instruments == {ONC_T: "HAYABUSA2_ONC-T"}
    assert (read.target, read.target_id) == ("(162173) Ryugu", 2162173)
    with kernel_pool(sorted((ryugu_sim / "truth" / "kernels").glob("*.tm"))):
        for view in read.views:  # the kernels of a downlink without knowledge errors are the truth's
            truth = camera_pose(et=view.et, instrument_id=ONC_T, target="RYUGU", body_frame="RYUGU_FIXED")
            assert np.allclose(view.pose.position, truth.position, atol=1e-9)
            assert np.allclose(view.pose.rotation, truth.rotation, atol=1e-9)
    # ONC-T's IK gives focal length and pixel size in mm: 121.1 / 0.013 px, 1 % off its FOV's
    assert read.views[0].camera.fx == pytest.approx(121.1 / 0.013)
    assert (read.views[0].camera.width, read.views[0].camera.height) == (320, 320)


def test_a_downlink_of_two_cameras_gives_each_image_its_own(ryugu_sim, tmp_path):
    downlink = copy_downlink(ryugu_sim, tmp_path)
    relabel(downlink, WIDE, "ONC-W1")
    read = read_downlink(downlink)
    assert read.instruments == {ONC_T: "HAYABUSA2_ONC-T", ONC_W1: "HAYABUSA2_ONC-W1"} and read.skipped == []
    mk = sorted(downlink.rglob("*.tm"))
    with kernel_pool(mk):
        for view in read.views:
            instrument = ONC_W1 if view.name.endswith(WIDE) else ONC_T
            product = read_image_product(downlink / "images" / f"{view.name}.xml")
            assert view.camera == camera_from_kernel(instrument).subframe(
                first_sample=product.first_sample, first_line=product.first_line, samples=product.samples,
                lines=product.lines)
            pose = camera_pose(et=view.et, instrument_id=instrument, target="RYUGU", body_frame="RYUGU_FIXED")
            assert np.allclose(view.pose.rotation, pose.rotation, atol=1e-12)
    wide = [v for v in read.views if v.name.endswith(WIDE)]
    narrow = [v for v in read.views if not v.name.endswith(WIDE)]
    # ONC-W1 sees 65 deg across, ONC-T 6.35 deg; the FK mounts them 0.35 deg apart
    assert all(v.camera.fx < 800 for v in wide) and all(v.camera.fx > 9000 for v in narrow)
    plain = {v.name: v for v in read_downlink(ryugu_sim / "downlink").views}
    turn = [np.degrees(np.arccos(np.clip((np.trace(v.pose.rotation @ plain[v.name].pose.rotation.T) - 1) / 2, -1, 1)))
            for v in wide]
    assert turn == pytest.approx([0.35] * len(wide), abs=0.02)


def test_ingest_catalogues_each_camera_of_a_downlink(ryugu_sim, tmp_path, open_catalog_at):
    downlink = copy_downlink(ryugu_sim, tmp_path)
    relabel(downlink, WIDE, "ONC-W1")
    sessions = open_catalog_at(f"sqlite:///{tmp_path / 'catalog.sqlite'}")
    report = ingest_directory(sessions, downlink)
    assert report.images.accepted == 6 and report.failures == []
    with sessions() as session:
        cameras = {i.naif_id: i for i in session.query(Instrument)}
        assert set(cameras) == {ONC_T, ONC_W1}
        assert cameras[ONC_W1].fx_px < 800 < 9000 < cameras[ONC_T].fx_px
        for image in session.query(Image):
            expected = ONC_W1 if Path(image.label_path).stem.endswith(WIDE) else ONC_T
            assert image.instrument.naif_id == expected and image.geometry.body_frame == "RYUGU_FIXED"


def test_bad_products_are_skipped_with_ingests_codes(ryugu_sim, tmp_path, shared_data, open_catalog_at):
    downlink = copy_downlink(ryugu_sim, tmp_path)
    expected = add_bad_products(downlink, shared_data)
    read = read_downlink(downlink)
    assert len(read.views) == 5
    assert {Path(s.path).name: s.code for s in read.skipped} == expected
    assert all(s.reason for s in read.skipped)
    sessions = open_catalog_at(f"sqlite:///{tmp_path / 'catalog.sqlite'}")
    ingested = ingest_directory(sessions, downlink)
    assert {Path(f.path).name: f.code for f in ingested.failures} == expected


def test_overrides_choose_among_what_the_labels_say(ryugu_sim, tmp_path):
    downlink = copy_downlink(ryugu_sim, tmp_path)
    relabel(downlink, WIDE, "ONC-W1")
    only = read_downlink(downlink, instrument="HAYABUSA2_ONC-T", target="1999JU3", body_frame="RYUGU_FIXED")
    assert sorted(v.name[-6:] for v in only.views) == ["img000", "img002", "img004", "img005"]
    assert {Path(s.path).stem[-6:]: s.code for s in only.skipped} == dict.fromkeys(WIDE, "other_instrument")
    # Bennu has a frame (IAU_BENNU) but no ephemeris in this downlink: nothing is left
    with pytest.raises(NoUsableImages, match=r"no usable images \(6 products skipped: 6 outside_coverage\)"):
        read_downlink(downlink, target="BENNU")
    with pytest.raises(ValueError, match="instrument 'MapCam' is not"):
        read_downlink(downlink, instrument="MapCam")


def test_nothing_usable_says_what_the_labels_name_and_the_kernels_define(ryugu_sim, tmp_path):
    downlink = copy_downlink(ryugu_sim, tmp_path)
    for label in (downlink / "images").glob("*.xml"):
        text = label.read_text().replace("<name>ONC-T</name>", "<name>AMICA</name>")
        label.write_text(text.replace("<name>HAYABUSA2</name>", "<name>HAYABUSA</name>"))
    with pytest.raises(NoUsableImages) as caught:
        read_downlink(downlink)
    message = str(caught.value)
    assert "6 no_kernels" in message  # HAYABUSA is a body SPICE knows, without an SPK here
    assert "no images of a known instrument: the labels name AMICA on HAYABUSA; the kernels define " in message
    assert "HAYABUSA2_ONC-T (-37100)" in message and "HAYABUSA2_ONC-W1 (-37110)" in message

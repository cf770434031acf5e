"""The proving ground's lidar (pwm.simulate.lidar) read back through pwm.io.lidar: spots from the
exact kernels agree with the true ones to the range noise, those from kernels with navigation
errors carry them (the bus's, not the camera's misalignment); rasters give each shot's
direction; the footprint averages ranges over the beam; shots that cannot be used are kept
with their reason; the images of a scenario are the same with the lidar on. And OLA's Level 2
layout, its directions through its scan mirror's CK in the same kernels."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import spiceypy as sp
from scipy.spatial.transform import Rotation

from pwm.io.lidar import read_lidar_product, read_lidar_table, write_lidar_product
from pwm.io.pds4 import ProductError
from pwm.io.spice_kernels import CkSegment, kernel_pool, write_ck
from pwm.knowledge import NavigationErrors
from pwm.lidar.shots import Invalid
from pwm.mesh import Mesh
from pwm.raytrace import RayTracer
from pwm.simulate.campaign import simulate
from pwm.simulate.lidar import LidarSpec, footprint_offsets, range_footprints
from pwm.simulate.scenarios import Scenario, get_scenario

NOISE_M = 0.05
TINY_LIDAR = get_scenario("tiny").model_copy(
    update={"lidar": LidarSpec(pattern="profile", shots_per_view=150, range_noise_m=NOISE_M)})


def _read(out: Path, scenario: Scenario):
    manifest = json.loads((out / "truth" / "manifest.json").read_text())
    metakernel = next((out / "downlink" / "kernels" / "mk").glob("*.tm"))
    with kernel_pool([metakernel]):
        product = read_lidar_product(out / "downlink" / manifest["lidar"]["label"], target=scenario.target,
                                     body_frame=scenario.body_frame)
    return manifest, product.shots, np.load(out / "truth" / "lidar_spots.npz")


@pytest.fixture(scope="module")
def tiny_lidar(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """tiny_sim's simulation (seed 3, start model) with a profiling lidar."""
    out = tmp_path_factory.mktemp("tiny-lidar") / "sim"
    simulate(out, scenario=TINY_LIDAR, seed=3, with_start_model=True)
    return out


def _digests(directory: Path, pattern: str) -> dict[str, str]:
    return {p.relative_to(directory).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(directory.rglob(pattern))}


def test_the_lidar_leaves_the_images_and_pose_kernels_alone(tiny_sim: Path, tiny_lidar: Path) -> None:
    for pattern in ("*.fits", "*.bsp", "*.bc", "*.npz"):
        before = _digests(tiny_sim / "downlink", pattern) | _digests(tiny_sim / "truth", pattern)
        after = _digests(tiny_lidar / "downlink", pattern) | _digests(tiny_lidar / "truth", pattern)
        after.pop("lidar_spots.npz", None)
        assert before and before == after, pattern
    assert not (tiny_sim / "downlink" / "lidar").exists() and (tiny_lidar / "downlink" / "lidar").is_dir()


def test_spots_through_exact_kernels_agree_with_the_truth_to_the_range_noise(tiny_lidar: Path) -> None:
    manifest, shots, truth = _read(tiny_lidar, TINY_LIDAR)
    assert len(shots) == 6 * 150 == manifest["lidar"]["shots"]
    # every shot kept; those with no return (dropouts, misses) marked by the product's flag
    np.testing.assert_array_equal(shots.valid, truth["returned"])
    assert set(np.unique(shots.invalid)) == {Invalid.VALID, Invalid.FLAGGED}
    assert 0.9 < shots.valid.mean() < 1.0
    v = shots.valid
    np.testing.assert_allclose(shots.et, truth["et"])
    np.testing.assert_allclose(shots.origin_km[v], truth["origin_km"][v], atol=1e-9)
    offset = shots.spots_km()[v] - truth["spot_km"][v]
    along = (offset * shots.direction[v]).sum(axis=1)
    across = np.linalg.norm(offset - along[:, None] * shots.direction[v], axis=1)
    assert across.max() < 1e-9  # km: the directions are the true ones
    assert 0.85 * NOISE_M < np.sqrt((along**2).mean()) * 1e3 < 1.15 * NOISE_M  # 700-odd draws: ~3% scatter
    np.testing.assert_allclose(shots.sigma_km, NOISE_M * 1e-3)  # from the simulated IK


def test_spots_through_navigation_kernels_carry_its_errors(tmp_path: Path) -> None:
    errors = NavigationErrors(along_m=3.0, cross_m=1.0, misalign_urad=50.0, drift_urad=20.0)
    out = tmp_path / "sim"
    simulate(out, scenario=TINY_LIDAR, seed=3, knowledge=errors)
    manifest, shots, truth = _read(out, TINY_LIDAR)
    v = shots.valid
    # each view's shots leave from where its kernels put the spacecraft: the true position plus
    # the drawn error (turned a little with the body over the window)
    view = np.searchsorted([im["et"] for im in manifest["images"]], shots.et - 60.0)
    drawn_m = np.array([im["knowledge_error"]["position_m"] for im in manifest["images"]])[view]
    moved_m = (shots.origin_km - truth["origin_km"]) * 1e3
    assert np.abs(moved_m - drawn_m).max() < 0.1 * np.linalg.norm(drawn_m, axis=1).max()
    offset_m = np.linalg.norm(shots.spots_km()[v] - truth["spot_km"][v], axis=1) * 1e3
    assert np.sqrt((offset_m**2).mean()) > 10 * NOISE_M
    # the lidar is aligned with the bus on its own: its beams are turned by the attitude's drift
    # (0 at the first image, 20 urad at the last), never by the camera's 50 urad misalignment
    turned_urad = np.arccos(np.clip((shots.direction[v] * truth["direction"][v]).sum(axis=1), -1, 1)) * 1e6
    assert turned_urad.max() < 20.5
    first = view[v] == 0
    assert first.any() and turned_urad[first].max() < 1.0


def test_footprint_averages_the_ranges_over_the_beam() -> None:
    # a ridge z = slope * |x| under a lidar at height h looking down: the central ray meets its
    # crest, the others its flanks further away; on flat ground the beam's ranges barely differ
    h, half, rays = 1.0, 0.02, 19
    x = np.linspace(-0.2, 0.2, 401)
    for slope in (0.0, 1.0):
        xx, yy = np.meshgrid(x, x)
        vertices = np.column_stack([xx.ravel(), yy.ravel(), slope * np.abs(xx.ravel())])
        i = np.arange(400)[:, None] * 401 + np.arange(400)[None, :]
        faces = np.concatenate([np.stack([i, i + 1, i + 402], -1).reshape(-1, 3),
                                np.stack([i, i + 402, i + 401], -1).reshape(-1, 3)])
        tracer = RayTracer(Mesh(vertices, faces))
        mean, centre, fraction = range_footprints(tracer, origins=np.array([[0.0, 0.0, h]]),
                                                  directions=np.array([[0.0, 0.0, -1.0]]), half_angle=half,
                                                  rays=rays)
        offsets = footprint_offsets(rays, half)
        # each ray's range along it, exactly, from its tangent offsets about the beam (the second
        # across the ridge, for a beam looking down -z)
        norm = np.sqrt(1 + np.tan(offsets[:, 0])**2 + np.tan(offsets[:, 1])**2)
        expected = (h * norm / (1 + slope * np.abs(np.tan(offsets[:, 1])))).mean()
        assert fraction[0] == 1.0 and centre[0] == pytest.approx(h, abs=1e-6)
        assert mean[0] == pytest.approx(expected, abs=1e-5)
        if slope:
            assert h - mean[0] > 100 * 1e-5  # a ridge nearer the lidar than its crest's range says
        else:
            assert abs(mean[0] - h) < half**2  # flat: only the beam's obliquity


def test_a_footprint_on_a_slope_ranges_its_centre() -> None:
    # a beam is symmetric about its axis: on a tilted plane its rays' ranges, nearer on one side
    # and further on the other, average to the central ray's (but for the beam's obliquity, of
    # the order of the half angle squared); rays whose centroid were off the axis would range a
    # point beside it, a pointing error of that offset (the seven-ray sunflower's: 0.087 of the
    # half angle, 1.7e-3 of the range here)
    h, half = 1.0, 0.02
    for rays in (7, 19, 2):
        assert np.allclose(footprint_offsets(rays, half).mean(axis=0), 0.0, atol=1e-15)
        assert np.allclose(footprint_offsets(rays, half)[0], 0.0)
    plane = Mesh(np.array([[-1.0, -1.0, -1.0], [1.0, -1.0, 1.0], [1.0, 1.0, 1.0], [-1.0, 1.0, -1.0]]),
                 np.array([[0, 1, 2], [0, 2, 3]]))  # z = x: a 45 degree slope
    mean, centre, _ = range_footprints(RayTracer(plane), origins=np.array([[0.0, 0.0, h]]),
                                       directions=np.array([[0.0, 0.0, -1.0]]), half_angle=half, rays=7)
    assert centre[0] == pytest.approx(h, abs=1e-6)  # Embree's hits are single precision
    assert abs(mean[0] - centre[0]) < 2 * half ** 2


def test_unusable_shots_are_kept_with_their_reason(tiny_lidar: Path, tmp_path: Path) -> None:
    manifest, shots, truth = _read(tiny_lidar, TINY_LIDAR)
    et, range_km = truth["et"].copy(), truth["range_km"].copy()
    flag = np.where(truth["returned"], 0, 2)
    picks = np.flatnonzero(truth["returned"])[:4]
    range_km[picks[0]] = np.nan  # not a number
    et[picks[1]] += 86400.0 * 30  # a month past the kernels
    range_km[picks[2]] = 500.0  # past the lidar's 100 km
    et[picks[3]] = np.inf
    label, _ = write_lidar_product(directory=tiny_lidar / "downlink" / "hostile", basename="hostile",
                                   lid="urn:nasa:pds:test:hostile", et=et, range_km=range_km, flag=flag,
                                   start_utc="2019-03-04T00:00:00", stop_utc="2019-03-06T00:00:00", mission="t",
                                   host_name="t", instrument_name="PWM_LIDAR", target_name="Bennu", title="t")
    metakernel = next((tiny_lidar / "downlink" / "kernels" / "mk").glob("*.tm"))
    with kernel_pool([metakernel]):
        read = read_lidar_product(label, target=TINY_LIDAR.target, body_frame=TINY_LIDAR.body_frame).shots
    assert [Invalid(c) for c in read.invalid[picks]] == [Invalid.NOT_FINITE, Invalid.OUTSIDE_KERNELS,
                                                         Invalid.RANGE_LIMITS, Invalid.NOT_FINITE]
    others = np.setdiff1d(np.arange(len(et)), picks)
    np.testing.assert_array_equal(read.invalid[others], shots.invalid[others])
    # an instrument the kernels do not know: the product is refused
    stranger, _ = write_lidar_product(directory=tmp_path, basename="stranger", lid="urn:nasa:pds:test:stranger",
                                      et=et[:5], range_km=range_km[:5], flag=flag[:5], start_utc="2019-03-04T00:00:00",
                                      stop_utc="2019-03-06T00:00:00", mission="t", host_name="t",
                                      instrument_name="NO_SUCH_LIDAR", target_name="Bennu", title="t")
    with kernel_pool([metakernel]), pytest.raises(ProductError) as err:
        read_lidar_product(stranger, target=TINY_LIDAR.target, body_frame=TINY_LIDAR.body_frame)
    assert err.value.code == "unknown_instrument"


def test_a_raster_gives_each_shot_its_direction_over_the_body(global_tiny_sim: Path) -> None:
    scenario = get_scenario("global-tiny")
    manifest, shots, truth = _read(global_tiny_sim, scenario)
    assert manifest["lidar"]["pattern"] == "raster" and len(shots) == 12 * 400
    v = shots.valid
    np.testing.assert_array_equal(v, truth["returned"])
    offset_m = (shots.spots_km()[v] - truth["spot_km"][v]) * 1e3
    assert np.sqrt((offset_m**2).sum(axis=1).mean()) < 1.2 * NOISE_M
    # each raster sweeps the body: its returns spread over most of the body's width
    view = np.arange(len(shots)) // 400
    radius = float(np.linalg.norm(truth["spot_km"][v], axis=1).max())
    for k in range(12):
        spots = shots.spots_km()[v & (view == k)]
        assert len(spots) > 100 and np.ptp(spots, axis=0).max() > radius


def _ola_product(directory: Path, rows: list[tuple[float, float, int, int]]) -> Path:
    """An OLA Level 2-like character table (et s, range mm, flag_status, laser_selection, and a
    text field between them that is not read) and its label."""
    directory.mkdir(parents=True, exist_ok=True)
    lines = "".join(f"{et:20.6f}{'2019-044T01:01:01.796':>24}{rng:14.3f}{flag:4d}{laser:4d}\r\n"
                    for et, rng, flag, laser in rows)
    (directory / "ola.tab").write_text(lines, newline="")
    fields = [("et", 1, 20, "ASCII_Real"), ("utc", 21, 24, "ASCII_String"), ("range", 45, 14, "ASCII_Real"),
              ("flag_status", 59, 4, "ASCII_Integer"), ("laser_selection", 63, 4, "ASCII_Integer")]
    field_xml = "".join(f"<Field_Character><name>{n}</name><field_location unit='byte'>{loc}</field_location>"
                        f"<data_type>{t}</data_type><field_length unit='byte'>{w}</field_length></Field_Character>"
                        for n, loc, w, t in fields)
    label = directory / "ola.xml"
    label.write_text(f"""<?xml version="1.0"?>
<Product_Observational xmlns="http://pds.nasa.gov/pds4/pds/v1">
<Identification_Area><logical_identifier>urn:nasa:pds:orex.ola:x</logical_identifier></Identification_Area>
<Observation_Area><Observing_System><Observing_System_Component><name>OLA</name><type>Instrument</type>
</Observing_System_Component></Observing_System></Observation_Area>
<File_Area_Observational><File><file_name>ola.tab</file_name></File>
<Table_Character><offset unit="byte">0</offset><records>{len(rows)}</records>
<record_delimiter>Carriage-Return Line-Feed</record_delimiter>
<Record_Character><fields>5</fields><groups>0</groups><record_length unit="byte">68</record_length>
{field_xml}</Record_Character></Table_Character></File_Area_Observational></Product_Observational>""")
    return label


def test_an_ola_level2_table_is_read_through_its_scan_mirror(tiny_lidar: Path, tmp_path: Path) -> None:
    manifest, _, truth = _read(tiny_lidar, TINY_LIDAR)
    et = truth["et"][::25]
    rows = [(float(t), 1000.0 + k, k % 4, k % 2) for k, t in enumerate(et)]
    table = read_lidar_table(_ola_product(tmp_path / "ola", rows))
    assert table.layout == "ola-l2" and table.frames == ("ORX_OLA_HIGH", "ORX_OLA_LOW")
    np.testing.assert_allclose(table.et, et, atol=1e-6)
    np.testing.assert_allclose(table.range_km, [r[1] * 1e-6 for r in rows])  # mm
    np.testing.assert_array_equal(table.flagged, [r[2] >= 2 for r in rows])  # 0, 1 (overflow) returns
    np.testing.assert_array_equal(table.frame_index, [r[3] for r in rows])
    # the mirror (ORX_OLA_ART, a CK frame) turned 0.1 rad about its X axis through every view
    windows = [im["et"] + np.array([-60.0, 0.0, 60.0]) for im in manifest["images"]]
    turn = Rotation.from_rotvec([0.1, 0.0, 0.0]).as_matrix()
    mirror = tmp_path / "ola_art.bc"
    metakernel = next((tiny_lidar / "downlink" / "kernels" / "mk").glob("*.tm"))
    with kernel_pool([metakernel]):  # its clock
        write_ck(mirror, segments=[CkSegment(frame_id=-64401, sclk_id=-64, epochs=np.concatenate(windows),
                                             rotations=np.repeat(turn[None], 3 * len(windows), axis=0),
                                             angular_velocities=np.zeros((3 * len(windows), 3)),
                                             interval_starts=[w[0] for w in windows], reference="ORX_OLA_BASE")])
    with kernel_pool([metakernel, mirror]):
        shots = read_lidar_product(tmp_path / "ola" / "ola.xml", target=TINY_LIDAR.target,
                                   body_frame=TINY_LIDAR.body_frame).shots
        base = np.array([sp.pxform("ORX_OLA_BASE", TINY_LIDAR.body_frame, float(t)) for t in et])
    # OLA's FK: +Z the boresight of its transmitters, aligned with the mirror's frame
    np.testing.assert_allclose(shots.direction, base @ turn.T @ [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(shots.origin_km, truth["origin_km"][::25], atol=1e-9)
    assert [Invalid(c) for c in shots.invalid[:4]] == [Invalid.VALID, Invalid.VALID, Invalid.FLAGGED,
                                                       Invalid.FLAGGED]
    # without the mirror's CK the kernels cannot turn the shots: marked, not guessed
    with kernel_pool([metakernel]):
        blind = read_lidar_product(tmp_path / "ola" / "ola.xml", target=TINY_LIDAR.target,
                                   body_frame=TINY_LIDAR.body_frame).shots
    assert set(blind.invalid[~table.flagged]) == {Invalid.OUTSIDE_KERNELS}

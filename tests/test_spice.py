"""SPICE kernels written by pwm read back through the geometry readers, and real kernels read."""

import shutil
import subprocess
import sys

import numpy as np
import pytest
import spiceypy as sp

from pwm.camera import look_at
from pwm.io.spice_geometry import (
    camera_from_kernel,
    camera_pose,
    coverage_ck,
    coverage_spk,
    spacecraft_of,
    sun_direction,
)
from pwm.io.spice_kernels import (
    CkSegment,
    KernelError,
    SpkSegment,
    bundled_kernels,
    kernel_pool,
    load_metakernel,
    metakernel_files,
    write_ck,
    write_metakernel,
    write_spk,
)

BENNU, SC, MAPCAM, SC_BUS = 2101955, -64, -64361, -64000
C_KM_S = 299792.458


def _body_fixed_states(t: np.ndarray) -> np.ndarray:
    """Spacecraft (n, 6) in IAU_BENNU: 5 km away, sweeping in longitude."""
    a, b, r, w = 0.3 + 2e-4 * t, 0.2, 5.0, 2e-4
    pos = r * np.stack([np.cos(a) * np.cos(b), np.sin(a) * np.cos(b), np.full_like(a, np.sin(b))],
                       axis=1)
    vel = r * w * np.stack([-np.sin(a) * np.cos(b), np.cos(a) * np.cos(b), np.zeros_like(a)], 1)
    return np.hstack([pos, vel])


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    """Kernels for two observation windows, in a directory deeper than 80 characters."""
    deep = tmp_path_factory.mktemp("spice") / ("kernels_" + "x" * 40) / ("deep_" + "y" * 40)
    deep.mkdir(parents=True)
    with kernel_pool(bundled_kernels().values()):
        et0 = sp.utc2et("2019-03-03T10:00:00")
        windows = [et0 + np.arange(0.0, 241.0, 60.0), et0 + 3600 + np.arange(0.0, 181.0, 60.0)]
        epochs = np.concatenate(windows)
        bf = _body_fixed_states(epochs - et0)
        to_j2000 = [sp.sxform("IAU_BENNU", "J2000", et) for et in epochs]
        sc_j2000 = np.array([m @ s for m, s in zip(to_j2000, bf, strict=True)])
        body_to_cam = np.array([look_at(s[:3], np.zeros(3), np.array([0.0, 0, 1])).rotation
                                for s in bf])
        struct = sp.eul2m(np.pi / 2, 0.01, -0.02, 3, 2, 1)  # ORX_SPACECRAFT -> MapCam, constant
        sc_att = np.array([struct.T @ r @ sp.pxform("J2000", "IAU_BENNU", et)
                           for r, et in zip(body_to_cam, epochs, strict=True)])
        split = len(windows[0])
        write_spk(deep / "sc.bsp", segments=[
            SpkSegment(SC, BENNU, epochs[:split], sc_j2000[:split]),
            SpkSegment(SC, BENNU, epochs[split:], sc_j2000[split:])])
        # Bennu wrt Sun wrt SSB, as in the real OSIRIS-REx SPKs: 'LT+S' needs the chain to the SSB.
        sun_epochs = et0 + np.arange(-600.0, 4201.0, 600.0)
        bennu_pos = 1.2 * 1.495978707e8 * np.array([1.0, 0.3, 0.1]) / np.linalg.norm([1, 0.3, 0.1])
        bennu_vel = 28.0 * np.array([-0.3, 1.0, 0.0]) / np.linalg.norm([-0.3, 1.0, 0.0])
        helio = np.hstack([bennu_pos + np.outer(sun_epochs - et0, bennu_vel),
                           np.tile(bennu_vel, (len(sun_epochs), 1))])
        write_spk(deep / "sun.bsp", segments=[
            SpkSegment(BENNU, 10, sun_epochs, helio),
            SpkSegment(10, 0, sun_epochs, np.zeros((len(sun_epochs), 6)))])
        write_ck(deep / "sc.bc", segments=[CkSegment(
            SC_BUS, SC, epochs, sc_att, np.zeros((len(epochs), 3)), [w[0] for w in windows])])
        write_ck(deep / "struct.bc", segments=[CkSegment(
            MAPCAM, SC, sun_epochs[[0, -1]], np.array([struct, struct]), np.zeros((2, 3)),
            [sun_epochs[0]], reference="ORX_SPACECRAFT")])
    kernels = [*bundled_kernels().values(), *(deep / n for n in
                                              ("sun.bsp", "sc.bsp", "sc.bc", "struct.bc"))]
    write_metakernel(deep / "pwm.tm", kernels=kernels)
    return dict(mk=deep / "pwm.tm", kernels=kernels, dir=deep, et0=et0, windows=windows,
                epochs=epochs, body_fixed=bf, body_to_cam=body_to_cam, bennu_vel=bennu_vel,
                bennu_pos=bennu_pos, sun_epochs=sun_epochs)


def test_pose_and_sun_round_trip(scenario):
    with kernel_pool([scenario["mk"]]):
        for et, state, rot in zip(scenario["epochs"], scenario["body_fixed"],
                                  scenario["body_to_cam"], strict=True):
            pose = camera_pose(et=et, instrument_id=MAPCAM, target="BENNU", body_frame="IAU_BENNU")
            assert np.abs(pose.position - state[:3]).max() < 1e-9
            # the image frame swaps the instrument's X and Y (MapCam samples run along +Y)
            assert np.abs(pose.rotation - rot[[1, 0, 2]]).max() < 1e-9
            helio = scenario["bennu_pos"] + (et - scenario["et0"]) * scenario["bennu_vel"]
            expected = sp.pxform("J2000", "IAU_BENNU", et) @ (-helio / np.linalg.norm(helio))
            sun = sun_direction(et=et, target="BENNU", body_frame="IAU_BENNU", abcorr="NONE")
            assert np.linalg.norm(sun - expected) < 1e-9


def test_sun_direction_is_aberrated_by_the_body_motion(scenario):
    """With the Sun fixed at the SSB, LT+S differs from geometric by stellar aberration only."""
    with kernel_pool([scenario["mk"]]):
        et = scenario["epochs"][2]
        kw = dict(et=et, target="BENNU", body_frame="IAU_BENNU")
        geometric, apparent = sun_direction(**kw, abcorr="NONE"), sun_direction(**kw)
        v = sp.pxform("J2000", "IAU_BENNU", et) @ scenario["bennu_vel"]
    angle = np.arccos(np.clip(geometric @ apparent, -1, 1))
    assert angle == pytest.approx(np.linalg.norm(np.cross(geometric, v)) / C_KM_S, rel=1e-3)
    assert (apparent - geometric) @ v > 0


def test_attitude_only_inside_observation_windows(scenario):
    windows = scenario["windows"]
    with kernel_pool([scenario["mk"]]):
        sp.pxform("IAU_BENNU", "ORX_OCAMS_MAPCAM", (windows[0][0] + windows[0][1]) / 2)
        with pytest.raises(sp.utils.exceptions.SpiceyError):
            sp.pxform("IAU_BENNU", "ORX_OCAMS_MAPCAM", (windows[0][-1] + windows[1][0]) / 2)


def test_coverage_windows_equal_written_windows(scenario):
    written = [(w[0], w[-1]) for w in scenario["windows"]]
    with kernel_pool([scenario["mk"]]):
        assert coverage_spk(scenario["dir"] / "sc.bsp", SC) == written
        assert np.allclose(coverage_ck(scenario["dir"] / "sc.bc", SC_BUS), written, rtol=0,
                           atol=1e-6)
        sun = scenario["sun_epochs"]
        assert np.allclose(coverage_ck(scenario["dir"] / "struct.bc", MAPCAM),
                           [(sun[0], sun[-1])], rtol=0, atol=1e-6)


def test_metakernel_loads_from_another_directory(scenario, tmp_path):
    """pwm reads the relative PATH_VALUES it writes against the meta-kernel from any working
    directory; SPICE itself, from the meta-kernel's directory."""
    assert len(str(scenario["dir"])) > 80
    assert metakernel_files(scenario["mk"]) == scenario["kernels"]
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    moved = elsewhere / "copy"
    shutil.copytree(scenario["dir"], moved)
    assert metakernel_files(moved / "pwm.tm")[-1] == moved / "struct.bc"  # a copy names its own
    script = ("import sys, spiceypy as sp; sp.furnsh(sys.argv[1]); "
              "print(sp.ktotal('ALL')); print(*sp.spkpos('-64', float(sys.argv[2]), 'IAU_BENNU', "
              "'NONE', 'BENNU')[0])")
    et = scenario["epochs"][0]
    out = subprocess.run([sys.executable, "-c", script, str(scenario["mk"]), repr(float(et))],
                         cwd=scenario["dir"], capture_output=True, text=True, check=True).stdout.split()
    assert int(out[0]) == len(scenario["kernels"]) + 1  # the meta-kernel counts itself
    assert np.allclose([float(x) for x in out[1:]], scenario["body_fixed"][0, :3], atol=1e-9)


def test_relative_path_values_resolve_against_the_metakernel(tmp_path, monkeypatch):
    """Archives ship PATH_VALUES = ( '..' ): relative to the meta-kernel, not the working dir."""
    (tmp_path / "archive" / "mk").mkdir(parents=True)
    (tmp_path / "archive" / "lsk").mkdir()
    lsk = tmp_path / "archive" / "lsk" / "naif0012.tls"
    lsk.write_bytes(bundled_kernels()["naif0012.tls"].read_bytes())
    mk = tmp_path / "archive" / "mk" / "test.tm"
    mk.write_text("KPL/MK\n\\begindata\n PATH_VALUES = ( '..' )\n PATH_SYMBOLS = ( 'KERNELS' )\n"
                  " KERNELS_TO_LOAD = ( '$KERNELS/lsk/naif0012.tls' )\n\\begintext\n")
    monkeypatch.chdir(tmp_path / "archive" / "lsk")  # '..' from here would miss the kernel
    with kernel_pool([]):
        assert load_metakernel(mk) == [lsk]
        assert sp.ktotal("ALL") == 1
        assert sp.deltet(0.0, "ET") == pytest.approx(64.184, abs=1e-3)  # the LSK is usable


def test_missing_kernels_are_listed_before_anything_loads(shared_data):
    mk = shared_data / "spice" / "mk" / "orx_2020_v05.tm"
    named = mk.read_text().count("'$KERNELS/")
    with kernel_pool([]):
        with pytest.raises(KernelError) as err:
            load_metakernel(mk)
        assert sp.ktotal("ALL") == 0
        assert not sp.expool("KERNELS_TO_LOAD")
    assert len(err.value.missing) == named
    assert err.value.missing[0] == shared_data / "spice" / "lsk" / "naif0012.tls"
    assert str(shared_data / "spice" / "fk" / "orx_v14.tf") in str(err.value)


def test_ck_quaternions_and_angular_velocity_follow_spice(tmp_path):
    """ckw03(m2q(C)) must give pxform('J2000', frame) == C; av is the frame's rate in J2000."""
    theta = 0.3
    assert np.allclose(sp.m2q(sp.rotate(theta, 3)), [np.cos(theta / 2), 0, 0, -np.sin(theta / 2)])
    rate, dt = 1e-3, 10.0
    with kernel_pool(bundled_kernels().values()):
        et0 = sp.utc2et("2019-03-03T10:00:00")
        t = np.arange(0.0, 61.0, dt)
        spin = np.array([sp.rotate(theta + rate * x, 3) for x in t])
        write_ck(tmp_path / "spin.bc", segments=[CkSegment(
            MAPCAM, SC, et0 + t, spin, np.tile([0.0, 0.0, rate], (len(t), 1)), [et0])])
        sp.furnsh(str(tmp_path / "spin.bc"))
        for x, c in zip(t, spin, strict=True):
            assert np.abs(sp.pxform("J2000", "ORX_OCAMS_MAPCAM", et0 + x) - c).max() < 1e-12
        mid = et0 + dt / 2  # between records; SCLK ticks round the time by ~1e-7 s
        assert np.abs(sp.pxform("J2000", "ORX_OCAMS_MAPCAM", mid)
                      - sp.rotate(theta + rate * dt / 2, 3)).max() < 1e-9
        _, av = sp.xf2rav(sp.sxform("J2000", "ORX_OCAMS_MAPCAM", mid))
    assert np.allclose(av, [0, 0, rate], atol=1e-12)


@pytest.mark.parametrize("kernel, instrument, focal_px, fov_half_tan", [
    # OCAMS: FOCAL_LENGTH mm, PIXEL_SIZE microns; FOV half-angles in degrees.
    ("bundled:orx_ocams_v07.ti", -64361, 125.20 / 8.5e-3, np.tan(np.radians(1.985))),
    ("bundled:orx_ocams_v07.ti", -64360, 628.70 / 8.5e-3, np.tan(np.radians(0.397))),
    # AMICA: both in metres; FOV corners (0.006144, 0.006144, 0.1204711614).
    ("hayabusa_amica_itokawa/amica31.ti", -130102, 0.1208 / 0.000012, 0.006144 / 0.1204711614),
    # Hayabusa2 ONC-T: both in mm.
    ("hyb2/hyb2_onc_v00.ti", -37100, 121.1 / 0.013, None),
])
def test_camera_focal_length_units_are_inferred(kernel, instrument, focal_px, fov_half_tan, shared_data):
    path = bundled_kernels()[kernel[8:]] if kernel.startswith("bundled:") else shared_data / "spice" / kernel
    with kernel_pool([path]):
        camera = camera_from_kernel(instrument)
    assert (camera.width, camera.height) == (1024, 1024)
    assert camera.fx == pytest.approx(focal_px, rel=1e-12)
    assert camera.fy == pytest.approx(focal_px, rel=1e-12)
    if fov_half_tan is not None:
        assert camera.fx == pytest.approx(512 / fov_half_tan, rel=0.02)


def test_camera_principal_point_and_fov_fallback():
    with kernel_pool([bundled_kernels()["orx_ocams_v07.ti"]]):
        assert (camera_from_kernel(MAPCAM).cx, camera_from_kernel(MAPCAM).cy) == (511.5, 511.5)
        sp.dvpool("INS-64361_FOCAL_LENGTH")
        assert camera_from_kernel(MAPCAM).fx == pytest.approx(512 / np.tan(np.radians(1.985)))
        sp.pdpool("INS-64361_FOCAL_LENGTH", [125.20 * 1.5])
        with pytest.raises(KernelError, match="no unit ratio"):
            camera_from_kernel(MAPCAM)


def test_spacecraft_of():
    assert [spacecraft_of(i) for i in (-64361, -64000, -130102, -37100)] == [-64, -64, -130, -37]
    with pytest.raises(ValueError):
        spacecraft_of(BENNU)


def test_real_mapcam_kernels_give_the_observed_range(shared_data):
    """A real MapCam image of 2019-03-03: about 6.6 km from Bennu, boresight on the body."""
    directory = shared_data / "spice" / "orex_mapcam_20190303"
    kernels = [bundled_kernels()["naif0012.tls"],
               *(p for p in sorted(directory.iterdir()) if p.suffix != ".lbl")]
    with kernel_pool(kernels):
        et = sp.utc2et("2019-03-03T10:59:40.279")
        pose = camera_pose(et=et, instrument_id=MAPCAM, target="BENNU", body_frame="IAU_BENNU")
        windows = coverage_spk(directory / "20190303T100344S990_map_iofL2pan_V001_1.bsp", SC)
        sun = sun_direction(et=et, target="BENNU", body_frame="IAU_BENNU")
    distance = np.linalg.norm(pose.position)
    assert 6.5 < distance < 6.7
    assert np.degrees(np.arccos(-pose.position @ pose.boresight / distance)) < 2.0
    assert np.allclose(pose.rotation @ pose.rotation.T, np.eye(3), atol=1e-12)
    assert any(start <= et <= stop for start, stop in windows)
    assert np.linalg.norm(sun) == pytest.approx(1.0)

"""Knowledge errors of a simulated downlink (pwm.simulate.knowledge): independent per image, or
navigation-like (smooth over arcs, a fixed misalignment and a drift), and that the kernels carry
exactly the errors the truth manifest records."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from pwm.io.spice_kernels import KernelError, SpkSegment, knowledge_comment, stated_knowledge, write_spk
from pwm.knowledge import (
    EXACT,
    RADIAL_FRACTION,
    IndependentErrors,
    NavigationErrors,
    parse_knowledge_errors,
    shared_frame_sigma,
)
from pwm.simulate.knowledge import perturb
from pwm.trajectory import ARC_GAP_S, along_arcs, arcs, track_frames
from service.settings import Settings

DAY = 86400.0


def orbit(times: np.ndarray, *, radius_km: float = 1.0, period_s: float = DAY) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities (body-fixed) on an inclined circular orbit, and random camera rotations."""
    phase = 2 * np.pi * times / period_s
    tilt = Rotation.from_rotvec([0.4, 0.2, 0.0]).as_matrix()
    pos = radius_km * np.stack([np.cos(phase), np.sin(phase), np.zeros_like(phase)], axis=1) @ tilt.T
    vel = np.stack([-np.sin(phase), np.cos(phase), np.zeros_like(phase)], axis=1) @ tilt.T
    return pos, vel


def synthetic(n: int = 200, step_s: float = 1200.0, start: float = 6e8) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                                  np.ndarray]:
    times = start + step_s * np.arange(n)
    pos, vel = orbit(times - start)
    rotations = Rotation.random(n, random_state=7).as_matrix()
    return times, pos, vel, rotations


NAV = NavigationErrors(along_m=3.0, cross_m=1.0, misalign_urad=50.0, drift_urad=20.0)


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def test_navigation_errors_are_smooth_and_mostly_along_track():
    times, pos, vel, rot = synthetic()
    drawn = perturb(NAV, times=times, positions_km=pos, rotations=rot, rng=np.random.default_rng(1))
    assert len(drawn.arcs) == 1  # 20-minute steps: one arc
    err = drawn.position_error_m
    np.testing.assert_allclose((drawn.positions_km - pos) * 1e3, err, atol=1e-9)
    # smooth: the second difference between consecutive images is far below the error itself, in the
    # along/cross/radial split and in body-fixed axes (which turn with the orbit, 5 degrees a step)
    assert np.abs(np.diff(drawn.track_error_m, 2, axis=0)).max() < 5e-3 * rms(err)
    assert np.abs(np.diff(err, 2, axis=0)).max() < 0.03 * rms(err)
    independent = perturb(IndependentErrors(3.0, 1e-4), times=times, positions_km=pos, rotations=rot,
                          rng=np.random.default_rng(1)).position_error_m
    assert np.abs(np.diff(independent, 2, axis=0)).max() > rms(independent)  # what an unsmooth error looks like
    # the RMS split, against the orbit's own directions (not the estimated ones the model used)
    along = np.einsum("ki,ki->k", err, vel)
    normal = np.cross(pos, vel)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    radial = pos / np.linalg.norm(pos, axis=1, keepdims=True)
    assert rms(along) == pytest.approx(3.0, rel=0.01)
    assert rms(np.einsum("ki,ki->k", err, normal)) == pytest.approx(1.0, rel=0.01)
    assert rms(np.einsum("ki,ki->k", err, radial)) == pytest.approx(RADIAL_FRACTION * 1.0, rel=0.02)
    np.testing.assert_allclose(np.sqrt(np.mean(drawn.track_error_m**2, axis=0)), [3.0, 1.0, RADIAL_FRACTION],
                               rtol=1e-9)


def test_attitude_is_one_misalignment_and_a_linear_drift():
    times, pos, _, rot = synthetic()
    drawn = perturb(NAV, times=times, positions_km=pos, rotations=rot, rng=np.random.default_rng(2))
    turns = drawn.rotations @ np.transpose(rot, (0, 2, 1))  # the pointing error of each image, as a rotation
    misalignment = Rotation.from_matrix(turns[0])  # the first image: no drift yet
    assert np.linalg.norm(misalignment.as_rotvec()) * 1e6 == pytest.approx(50.0, rel=1e-9)
    np.testing.assert_allclose(misalignment.as_rotvec(), drawn.misalignment_rad, atol=1e-15)
    # what is left after the same misalignment for every image is a drift linear in time
    drift = (misalignment.inv() * Rotation.from_matrix(turns)).as_rotvec()
    fraction = (times - times[0]) / (times[-1] - times[0])
    np.testing.assert_allclose(drift, fraction[:, None] * drift[-1], atol=1e-13)
    assert np.linalg.norm(drift[-1]) * 1e6 == pytest.approx(20.0, rel=1e-9)
    np.testing.assert_allclose(drift, drawn.drift_rad, atol=1e-13)
    # the recorded pointing errors are these rotations, in the instrument frame and body-fixed
    np.testing.assert_allclose(Rotation.from_rotvec(drawn.pointing_error_rad).as_matrix(), turns, atol=1e-15)
    body = np.einsum("kji,kj->ki", rot, drawn.pointing_error_rad)
    np.testing.assert_allclose(rot @ Rotation.from_rotvec(body).as_matrix(), drawn.rotations, atol=1e-15)


def test_arcs_split_at_gaps_and_each_has_its_rms():
    times = np.concatenate([6e8 + 3600.0 * np.arange(10), 6e8 + 5 * DAY + 3600.0 * np.arange(8), [6e8 + 9 * DAY]])
    shuffled = np.random.default_rng(0).permutation(len(times))
    times = times[shuffled]
    pos, _ = orbit(times - 6e8)
    rot = Rotation.random(len(times), random_state=1).as_matrix()
    groups = arcs(times, gap_s=ARC_GAP_S)
    assert [len(g) for g in groups] == [10, 8, 1]
    assert all((np.diff(times[g]) > 0).all() for g in groups)
    drawn = perturb(NAV, times=times, positions_km=pos, rotations=rot, rng=np.random.default_rng(3))
    for g in groups:
        np.testing.assert_allclose(np.sqrt(np.mean(drawn.track_error_m[g] ** 2, axis=0)),
                                   [3.0, 1.0, RADIAL_FRACTION], rtol=1e-9)
    # an arc of one image: along-track is perpendicular to its position and the spin axis
    (lone,) = groups[2]
    frame = track_frames(times, pos)[lone]
    assert abs(frame[0] @ pos[lone]) < 1e-12 and abs(frame[0][2]) < 1e-12
    np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(frame) == pytest.approx(1.0)


def test_independent_errors_draw_what_the_campaign_always_drew():
    times, pos, _, rot = synthetic(n=7)
    drawn = perturb(IndependentErrors(position_m=2.0, pointing_rad=3e-4), times=times, positions_km=pos,
                    rotations=rot, rng=np.random.default_rng(11))
    rng = np.random.default_rng(11)  # the campaign's former _perturb, inline
    for k in range(len(times)):
        dpos = rng.normal(0.0, 2.0 * 1e-3, 3)
        drot = Rotation.from_rotvec(rng.normal(0.0, 3e-4, 3)).as_matrix()
        assert np.array_equal(drawn.positions_km[k], pos[k] + dpos)
        assert np.array_equal(drawn.rotations[k], drot @ rot[k])
    assert drawn.misalignment_rad.tolist() == [0.0, 0.0, 0.0]


def test_parse_knowledge_errors():
    assert parse_knowledge_errors("1,1e-4") == IndependentErrors(1.0, 1e-4)
    assert parse_knowledge_errors("nav:3,1,50,20") == NAV
    assert parse_knowledge_errors(" NAV: 3, 1, 50, 20 ") == NAV


@pytest.mark.parametrize(("value", "message"), [
    ("nav:3,1,-50,20", "misalign_urad must be a finite non-negative number"),
    ("nav:3,nan,50,20", "cross_m must be a finite non-negative number"),
    ("nav:inf,1,50,20", "along_m must be a finite non-negative number"),
    ("-1,1e-4", "position_m must be a finite non-negative number"),
    ("nav:3,1,50", "3 value(s) in 'nav:3,1,50', 4 wanted"),
    ("1,1e-4,3", "3 value(s) in '1,1e-4,3', 2 wanted"),
    ("orbit:3,1,50,20", "unknown knowledge-error mode 'orbit'"),
    ("nav:3,1,fifty,20", "misalign_urad 'fifty' is not a number"),
])
def test_bad_knowledge_errors_are_refused_by_the_command(tmp_path, value, message):
    from service.cli import app

    out = tmp_path / "sim"
    result = CliRunner().invoke(app, ["simulate", str(out), "--scenario", "tiny", "--knowledge-error", value])
    assert result.exit_code == 2, result.output
    text = " ".join(result.output.replace("│", " ").split())  # the rich box wraps the message
    assert "--knowledge-error" in text and " ".join(message.split()) in text, text
    assert not out.exists()


def test_navigation_kernels_carry_exactly_the_recorded_errors(tmp_path, tiny_sim):
    from pwm.io.spice_geometry import camera_pose
    from pwm.io.spice_kernels import kernel_pool
    from service.cli import app

    out = tmp_path / "sim"
    result = CliRunner().invoke(app, ["simulate", str(out), "--scenario", "tiny", "--seed", "3",
                                      "--knowledge-error", "nav:3,1,50,20"])
    assert result.exit_code == 0, result.output
    manifest = json.loads((out / "truth" / "manifest.json").read_text())
    summary = manifest["knowledge_error"]
    assert summary["mode"] == "navigation"
    # without --with-start-model, as a mission's first downlinks: no shape model delivered
    assert not (out / "downlink" / "start_model.obj").exists() and manifest["start_model"]["file"] is None
    assert (summary["along_m"], summary["cross_m"], summary["misalign_urad"], summary["drift_urad"]) == (3, 1, 50, 20)
    assert np.linalg.norm(summary["misalignment_urad"]) == pytest.approx(50.0)
    assert [len(a["images"]) for a in summary["arcs"]] == [manifest["image_count"]]  # 2 days of images: one arc
    (mk,) = (out / "downlink" / "kernels" / "mk").glob("*.tm")
    with kernel_pool([mk]):
        for image in manifest["images"]:
            recorded = image["knowledge_error"]
            pose = camera_pose(et=image["et"], instrument_id=-64361, target="BENNU", body_frame="IAU_BENNU")
            offset_m = (pose.position - np.array(image["position_km"])) * 1e3
            np.testing.assert_allclose(offset_m, recorded["position_m"], atol=1e-3)
            # downlink rotation = true rotation @ Rot(body-fixed error)
            turn = Rotation.from_matrix(np.array(image["rotation"]).T @ pose.rotation).as_rotvec() * 1e6
            np.testing.assert_allclose(turn, recorded["pointing_body_urad"], atol=0.1)
            assert np.linalg.norm(recorded["pointing_urad"]) == pytest.approx(np.linalg.norm(turn), abs=0.1)
    track = np.array([[i["knowledge_error"][k] for k in ("along_m", "cross_m", "radial_m")]
                      for i in manifest["images"]])
    np.testing.assert_allclose(np.sqrt(np.mean(track**2, axis=0)), [3.0, 1.0, RADIAL_FRACTION], rtol=1e-9)
    # the images are rendered from the truth: the same as those of the same seed without errors
    for data in sorted((tiny_sim / "downlink" / "images").glob("*.fits")):
        assert (out / "downlink" / "images" / data.name).read_bytes() == data.read_bytes(), data.name


def test_manifest_keeps_the_independent_keys(tiny_sim: Path):
    summary = json.loads((tiny_sim / "truth" / "manifest.json").read_text())["knowledge_error"]
    assert summary == {"mode": "independent", "position_m": 0.0, "pointing_rad": 0.0}


def test_kernels_state_their_pose_knowledge(tmp_path):
    epochs = np.array([0.0, 60.0, 120.0])
    states = np.column_stack([np.ones((3, 3)), np.zeros((3, 3))])
    for errors in (NAV, IndependentErrors(position_m=1.5, pointing_rad=2e-4)):
        path = tmp_path / "stated.bsp"
        write_spk(path, segments=[SpkSegment(body=-64, center=2101955, epochs=epochs, states=states)],
                  comments=["navigation delivery 7", knowledge_comment(errors)])
        assert stated_knowledge(path) == errors
    write_spk(tmp_path / "silent.bsp", segments=[SpkSegment(body=-64, center=2101955, epochs=epochs, states=states)])
    assert stated_knowledge(tmp_path / "silent.bsp") is None
    write_spk(tmp_path / "garbled.bsp", segments=[SpkSegment(body=-64, center=2101955, epochs=epochs, states=states)],
              comments=["PWM_POSE_KNOWLEDGE = nav:3,1"])
    with pytest.raises(KernelError, match="garbled.bsp: PWM_POSE_KNOWLEDGE: 2 value"):
        stated_knowledge(tmp_path / "garbled.bsp")
    (tmp_path / "text.bsp").write_text("not a DAF")
    with pytest.raises(KernelError, match="text.bsp"):
        stated_knowledge(tmp_path / "text.bsp")


def test_the_configured_pose_knowledge_is_checked(monkeypatch, tmp_path):
    monkeypatch.setenv("PWM_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("PWM_POSE_KNOWLEDGE", "nav:3,1,50,20")
    assert Settings().refinement().knowledge == NAV
    monkeypatch.setenv("PWM_POSE_KNOWLEDGE", "nav:3,-1,50,20")
    with pytest.raises(ValueError, match="cross_m must be a finite non-negative number"):
        Settings()
    monkeypatch.delenv("PWM_POSE_KNOWLEDGE")
    assert Settings().refinement().knowledge is None


def test_a_shared_frame_is_placed_as_well_as_one_pose():
    """What an instrument places under pose knowledge shares it (pwm.knowledge.shared_frame_sigma):
    the largest position sigma and the pointing's at the range, together (the bus's drift, not
    the camera's misalignment); the turn over the radius."""
    shift, turn = shared_frame_sigma(NavigationErrors(along_m=3, cross_m=1, misalign_urad=30, drift_urad=40),
                                     range_km=20.0, radius_km=0.25)
    assert shift == pytest.approx(np.hypot(3e-3, 40e-6 * 20.0)) and turn == pytest.approx(shift / 0.25)
    assert shared_frame_sigma(IndependentErrors(position_m=2.0, pointing_rad=0.0), range_km=5.0,
                              radius_km=1.0) == pytest.approx((2e-3, 2e-3))
    assert shared_frame_sigma(EXACT, range_km=5.0, radius_km=1.0) == (0.0, 0.0)


def test_values_are_interpolated_along_their_arcs_only():
    """pwm.trajectory.along_arcs: linear in time within an arc, its end values up to a gap beyond
    its ends, nothing between arcs further apart than that."""
    times = np.array([0.0, 100.0, 10 * ARC_GAP_S, 10 * ARC_GAP_S + 100.0])
    values = np.array([[0.0], [1.0], [5.0], [7.0]])
    at = np.array([50.0, -10.0, 100.0 + ARC_GAP_S / 2, 5 * ARC_GAP_S, 10 * ARC_GAP_S + 50.0])
    np.testing.assert_allclose(along_arcs(at, times, values)[:, 0], [0.5, 0.0, 1.0, 0.0, 6.0])

"""The proving ground's camera imperfections (pwm.simulate.optics) and the start model's smooth
undulations (pwm.simulate.truth.undulations)."""

from __future__ import annotations

import numpy as np
import pytest

from pwm.simulate.optics import Optics, blur, flat_field, smear_kernel


def test_blur_keeps_energy_and_spreads_a_point_as_its_sigma_says():
    point = np.zeros((41, 41))
    point[20, 20] = 1.0
    out = blur(point, Optics(psf_sigma_px=1.5))
    assert out.sum() == pytest.approx(1.0, rel=1e-9)
    y, x = np.mgrid[:41, :41]
    assert np.sqrt((out * (x - 20) ** 2).sum()) == pytest.approx(1.5, rel=0.02)
    assert np.array_equal(blur(point, Optics()), point)


@pytest.mark.parametrize("length, azimuth", [(3.0, 0.0), (5.0, 90.0), (4.0, 30.0)])
def test_the_smear_kernel_is_a_segment_of_its_length_and_direction(length, azimuth):
    kernel = smear_kernel(length, azimuth)
    assert kernel.sum() == pytest.approx(1.0) and (kernel >= 0).all()
    c = kernel.shape[0] // 2
    y, x = np.mgrid[: kernel.shape[0], : kernel.shape[1]] - c
    along = x * np.cos(np.radians(azimuth)) + y * np.sin(np.radians(azimuth))
    across = -x * np.sin(np.radians(azimuth)) + y * np.cos(np.radians(azimuth))
    # a uniform segment from -L/2 to L/2 has variance L^2 / 12 along, (bilinear spread aside) little across
    assert np.sqrt((kernel * along**2).sum()) == pytest.approx(length / np.sqrt(12), abs=0.3)
    assert np.sqrt((kernel * across**2).sum()) < 0.45
    assert abs((kernel * along).sum()) < 1e-9


def test_the_flat_field_has_its_rms_and_is_fixed_by_its_generator():
    field = flat_field((200, 300), 0.01, np.random.default_rng(3))
    assert field.mean() == pytest.approx(1.0, abs=0.003)
    assert field.std() == pytest.approx(0.01, rel=0.15)
    np.testing.assert_array_equal(field, flat_field((200, 300), 0.01, np.random.default_rng(3)))
    assert np.array_equal(flat_field((4, 4), 0.0, np.random.default_rng(0)), np.ones((4, 4)))


def test_optics_refuse_what_no_camera_does():
    with pytest.raises(ValueError):
        Optics(psf_sigma_px=-1)
    with pytest.raises(ValueError):
        Optics(flat_field_rms=0.5)

"""The compiled sums of registration against the same sums made of `bilinear` samples by numpy,
at the frame's edges, next to a NaN pixel and at a node behind the camera."""

from __future__ import annotations

import numpy as np
import pytest

from pwm.photoclinometry import MapletImages, bilinear
from pwm.registration_sums import normal_sums, shift_sums


def _sums_by_part(x: np.ndarray, labels: np.ndarray, parts: int) -> np.ndarray:
    return np.stack([x[..., labels == p].sum(axis=-1) for p in range(parts)], axis=-1)


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(4)
    image = rng.uniform(0.01, 0.05, (40, 50))
    image[12, 20] = np.nan
    pixels = np.column_stack([rng.uniform(-4.0, 53.0, 500), rng.uniform(-4.0, 43.0, 500)])
    pixels[:4] = [[np.nan, np.nan], [49.0, 39.0], [0.0, 0.0], [45.0, 35.5]]
    return image, pixels, rng.uniform(0.2, 1.0, 500), rng.integers(0, 3, 500)


def test_sums_at_every_whole_shift_are_those_of_bilinear_samples(scene) -> None:
    image, pixels, model, labels = scene
    reach = 3
    shifts = np.arange(-reach, reach + 1).astype(float)
    grid = np.stack(np.meshgrid(shifts, shifts), axis=-1)[:, :, None, :]  # [line shift, sample shift]
    samples = bilinear(image, pixels + grid)
    assert 0.05 < np.isnan(samples).mean() < 0.5
    ok = np.isfinite(samples)
    a, b = np.where(ok, samples, 0.0), np.where(ok, model, 0.0)
    expected = [_sums_by_part(x, labels, 3) for x in (ok.astype(float), a, b, a * a, b * b, a * b)]
    found = shift_sums(image, pixels, model, labels, 3, reach)
    assert found.shape == (6, 7, 7, 3)
    for got, want in zip(found, expected, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-15)


def test_normal_sums_are_gauss_newtons_of_central_differences(scene) -> None:
    image, pixels, model, labels = scene
    offsets = np.array([[0.3, -0.2], [-1.7, 0.6], [0.0, 0.0]])
    gain, bias = np.array([0.04, 0.05, 0.06]), np.array([0.001, -0.002, 0.0])
    active = np.array([True, True, False])
    found = normal_sums(image, pixels, offsets, labels, active, model, gain, bias)
    at = pixels + offsets[labels]
    values = bilinear(image, at)
    half = np.array([[0.5, 0.0], [0.0, 0.5]])
    grad = np.stack([bilinear(image, at + d) - bilinear(image, at - d) for d in half], axis=-1)
    ok = np.isfinite(values) & np.isfinite(grad).all(axis=1) & active[labels]
    assert 0.5 < ok[active[labels]].mean() < 0.95
    jac = np.where(ok[:, None], np.column_stack([grad, -model, -np.ones(len(model))]), 0.0)
    resid = np.where(ok, values - gain[labels] * model - bias[labels], 0.0)
    rows = np.vstack([ok, (jac[:, :, None] * jac[:, None, :]).reshape(-1, 16).T, (jac * resid[:, None]).T])
    np.testing.assert_allclose(found, _sums_by_part(rows, labels, 3).T, rtol=1e-12, atol=1e-15)
    assert not found[2].any()  # an inactive part adds nothing


def test_images_are_held_as_native_doubles() -> None:
    # the compiled sums take native doubles: a PDS4 product's big-endian singles are converted
    image = np.arange(12, dtype=">f4").reshape(3, 4)
    data = MapletImages(images=[image], cameras=[None], poses=[None], sun_directions=np.array([0.0, 0.0, 1.0]),
                        visible=np.ones((1, 2, 2), bool), lit=np.ones((1, 2, 2), bool), weights=np.ones((1, 2, 2)))
    assert data.images[0].dtype == np.dtype(float) and data.images[0].flags.c_contiguous
    np.testing.assert_array_equal(data.images[0], image)

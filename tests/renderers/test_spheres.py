"""The render-space metrics (neural_brdf.renderers.spheres): the quadrature render and its metrics.

The references here are physics and geometry stated in the tests: a white furnace
(a Lambertian sphere under a uniform sky shows its albedo), the mirror direction of a
single light, and the sRGB/PSNR definitions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from neural_brdf.renderers import spheres


def lambert(albedo):
    def f(wi, wo):
        up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        return np.where(up[:, None], np.asarray(albedo, np.float32) / math.pi, 0.0)

    return f


def phong_mirror(exponent: float):
    """A normalised Phong lobe around the mirror direction of wo (a test-side BRDF)."""

    def f(wi, wo):
        r = wo * np.array([-1.0, -1.0, 1.0])  # mirror of wo about the normal
        c = np.clip(np.sum(wi * r, -1), 0.0, None) ** exponent
        val = (exponent + 2) / (2 * math.pi) * c / np.maximum(wi[:, 2], 1e-6)
        up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        return np.repeat(np.where(up, val, 0.0)[:, None], 3, -1)

    return f


def test_white_furnace_shows_the_albedo():
    """Uniform sky of radiance 1: irradiance pi on every normal, so a Lambertian sphere of
    albedo rho has radiance rho at every pixel (the quadrature of the cosine to 1.5 %)."""
    dirs, _ = spheres.environment()
    # radiance 1 everywhere: divide out the sky's radiance, keep the solid angles
    height = spheres.ENV_HEIGHT
    el = math.pi * (0.5 - (np.arange(height) + 0.5) / height)
    omega = np.repeat((math.pi / height) ** 2 * np.cos(el), 2 * height)
    assert np.isclose(omega.sum(), 4 * math.pi, rtol=2e-3)  # the texels tile the sphere
    env = (dirs, np.repeat(omega[:, None], 3, -1))
    albedo = [0.8, 0.5, 0.2]
    img = spheres.render(lambert(albedo), resolution=24, env=env)
    mask, _ = spheres.sphere(24)
    assert mask.sum() == pytest.approx(math.pi * 12 * 12, rel=0.05)
    np.testing.assert_allclose(img[mask], np.broadcast_to(albedo, img[mask].shape), rtol=0.015)
    assert not img[~mask].any()


@pytest.mark.parametrize("el_deg, az_deg", [(30.0, 40.0), (-20.0, -60.0), (60.0, 170.0)])
def test_a_sharp_lobe_reflects_the_light_where_the_normal_bisects(el_deg, az_deg):
    """One light in direction d: a near-mirror sphere is brightest where the normal is the
    half vector of d and the camera (+z), at image column (h_x + 1) R / 2 and row
    (1 - h_y) R / 2 (rows run top to bottom, +y up)."""
    el, az = math.radians(el_deg), math.radians(az_deg)
    d = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    h = d + np.array([0.0, 0.0, 1.0])
    h /= np.linalg.norm(h)
    res = 64
    img = spheres.render(phong_mirror(2000.0), resolution=res, env=(d[None], np.ones((1, 3))))
    row, col = np.unravel_index(np.argmax(img[..., 0]), img.shape[:2])
    assert abs(col + 0.5 - (h[0] + 1) * res / 2) <= 1.0
    assert abs(row + 0.5 - (1 - h[1]) * res / 2) <= 1.0


def test_the_sun_lights_the_default_sphere():
    """The default sky: a grey Lambertian sphere is brighter where the normal faces the sun
    than where it faces the ground, and every channel is positive on the sphere."""
    img = spheres.render(lambert([0.5, 0.5, 0.5]), resolution=32)
    mask, frames = spheres.sphere(32)
    sun_el, sun_az, _ = spheres.SUN
    el, az = math.radians(sun_el), math.radians(sun_az)
    sun = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    lum = img[mask].mean(-1)
    facing = frames[:, 2] @ sun
    assert (img[mask] > 0).all()
    assert lum[np.argmax(facing)] > 2 * lum[np.argmin(frames[:, 2, 1])]


def _srgb(x):
    # IEC 61966-2-1, written out here independently of the module
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def test_metrics_psnr_and_flip():
    mask, _ = spheres.sphere(32)
    ref = np.zeros((32, 32, 3))
    ref[mask] = 0.09  # exposure maps the mean to 0.18: a scale of 2
    same = spheres.metrics(ref, ref.copy())
    assert same["psnr_db"] == math.inf
    assert same["flip"] == 0.0
    near, far = ref * 1.05, ref * 1.5
    m_near, m_far = spheres.metrics(ref, near), spheres.metrics(ref, far)
    expected = -20 * math.log10(abs(_srgb(0.18 * 1.05) - _srgb(0.18)))
    assert m_near["psnr_db"] == pytest.approx(expected, rel=1e-9)
    assert m_far["psnr_db"] < m_near["psnr_db"]
    assert 0.0 < m_near["flip"] < m_far["flip"] <= 1.0


def test_metrics_reject_mismatched_images():
    with pytest.raises(ValueError, match="shapes differ"):
        spheres.metrics(np.ones((8, 8, 3)), np.ones((16, 16, 3)))


def test_environment_texels_carry_their_solid_angle():
    """Radiance times solid angle summed over the ground (uniform radiance 0.18 + 0.05
    fill, per the scene's definition) is that radiance times 2 pi."""
    dirs, light = spheres.environment()
    ground = dirs[:, 1] < 0
    np.testing.assert_allclose(
        light[ground].sum(0), (np.array([0.18, 0.16, 0.14]) + 0.05) * 2 * math.pi, rtol=5e-3
    )

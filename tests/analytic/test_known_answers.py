"""Known answers from independent sources (tests/data, see its README).

Sources and tolerances:
  * Blender Cycles table_ggx_E / table_ggx_Eavg (Monte Carlo, 2^23 / 2^26 samples):
    GGX, height-correlated Smith, F = 1.  2e-3 absolute, as the issue asks.  The
    mu = 0 row and cells with alpha < 1e-3 at mu < 0.1 are skipped, as the data
    README says (the table clamps both to 1e-4, so those cells are not what their
    labels say).
  * Mitsuba 3.9.1 printed values (7 significant digits): GGX D, Smith G1, conductor
    Fresnel; 1e-5 relative.
  * A tutorial's exercises (docs/references.md; hand-computed to 3 digits):
    GGX D(30 deg, 0.3) ~ 0.284,
    Schlick F(60 deg, eta 1.5) ~ 0.07.
"""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
import torch

import analytic
from analytic import fresnel as fr
from analytic.microfacet import Distribution, _ms_table
from analytic.physics import projected_area, weak_white_furnace


def read_table(path):
    with open(path) as fh:
        rows = [r for r in csv.reader(line for line in fh if not line.startswith("#"))]
    return rows[0], rows[1:]


@pytest.fixture(scope="module")
def cycles_E(data_dir):
    head, rows = read_table(data_dir / "cycles_ggx_E_32x32.csv")
    r = np.array([float(x) for x in head[1:]])
    tab = np.array([[float(x) for x in row] for row in rows])
    return tab[:, 0], r, tab[:, 1:]


def test_cycles_ggx_directional_albedo(cycles_E):
    mu_all, r, E = cycles_E
    worst = 0.0
    for j in range(len(r)):
        alpha = max(r[j] ** 2, 1e-4)
        rows = [i for i in range(1, len(mu_all)) if not (alpha < 1e-3 and mu_all[i] < 0.1)]
        mu = mu_all[rows]
        brdf = analytic.create(
            "microfacet",
            distribution="ggx",
            alpha=alpha,
            masking="smith_correlated",
            fresnel="none",
        )
        wi = np.stack([np.sqrt(1 - mu * mu), np.zeros_like(mu), mu], -1)
        ours, err = analytic.albedo(brdf, wi, n=8192, return_error=True)
        assert err.max() < 6e-4, "quadrature too noisy for a 2e-3 comparison"
        diff = np.abs(ours[:, 0] - E[rows, j])
        worst = max(worst, diff.max())
        assert diff.max() <= 2e-3, (
            f"r={r[j]:.4f} mu={mu[np.argmax(diff)]:.4f}: "
            f"ours {ours[np.argmax(diff), 0]:.5f} vs Cycles "
            f"{E[rows, j][np.argmax(diff)]:.5f}"
        )


def test_cycles_ggx_average_albedo(data_dir):
    _, rows = read_table(data_dir / "cycles_ggx_Eavg_32.csv")
    for r, alpha, e_avg in ((float(a), float(b), float(c)) for a, b, c in rows):
        if alpha < 1e-3:
            continue
        ours = _ms_table("ggx", alpha, alpha, "smith_correlated").e_avg
        assert abs(ours - e_avg) <= 2e-3, f"r={r}: Eavg {ours:.5f} vs Cycles {e_avg:.5f}"


def test_ggx_known_albedo_values():
    """E(mu=1, alpha=1) = 0.306853 and Eavg(alpha=1) = 0.40914 (data README)."""
    brdf = analytic.create("microfacet", alpha=1.0)
    e = analytic.albedo(brdf, np.array([0.0, 0.0, 1.0]), n=65536)
    assert abs(e[0] - 0.306853) < 2e-4
    assert abs(_ms_table("ggx", 1.0, 1.0, "smith_correlated").e_avg - 0.40914) < 1e-3


def mitsuba_rows(data_dir, kind):
    with open(data_dir / "mitsuba3_reference_values.csv") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    return [r for r in rows if r["kind"] == kind]


def test_ggx_D_matches_mitsuba(data_dir):
    rows = mitsuba_rows(data_dir, "ggx_D")
    assert len(rows) >= 10
    for r in rows:
        d = Distribution("ggx", float(r["alpha_u"]), float(r["alpha_v"]))
        h = torch.tensor(
            [float(r["wo_x"]), float(r["wo_y"]), float(r["wo_z"])], dtype=torch.float64
        )
        ours, ref = d.D(h).item(), float(r["v_r"])
        assert ours == pytest.approx(ref, rel=1e-5, abs=1e-9), r


def test_ggx_G1_matches_mitsuba(data_dir):
    rows = mitsuba_rows(data_dir, "ggx_smith_G1")
    assert len(rows) >= 10
    for r in rows:
        d = Distribution("ggx", float(r["alpha_u"]), float(r["alpha_v"]))
        w = torch.tensor(
            [float(r["wo_x"]), float(r["wo_y"]), float(r["wo_z"])], dtype=torch.float64
        )
        assert d.G1(w).item() == pytest.approx(float(r["v_r"]), rel=1e-5), r


def mitsuba_ior(data_dir):
    with open(data_dir / "conductor_ior_rgb_mitsuba3.csv") as fh:
        rows = csv.DictReader(line for line in fh if not line.startswith("#"))
        return {
            r["material"]: (
                [float(r[f"eta_{c}"]) for c in "rgb"],
                [float(r[f"k_{c}"]) for c in "rgb"],
            )
            for r in rows
        }


def test_conductor_fresnel_matches_mitsuba(data_dir):
    ior = mitsuba_ior(data_dir)
    rows = mitsuba_rows(data_dir, "fresnel_conductor")
    assert len(rows) == 20
    for r in rows:
        eta, k = ior[r["material"]]
        cos = torch.tensor(float(r["cos_theta"]), dtype=torch.float64)
        ours = fr.conductor(eta, k, cos).numpy()
        ref = [float(r["v_r"]), float(r["v_g"]), float(r["v_b"])]
        np.testing.assert_allclose(ours, ref, rtol=1e-5, err_msg=str(r))


def test_gold_normal_incidence_known_answer(data_dir):
    eta, k = mitsuba_ior(data_dir)["Au"]
    f = fr.conductor(eta, k, torch.tensor(1.0, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(f, [0.96668, 0.80201, 0.32412], atol=1e-5)


@pytest.mark.parametrize("material", ["Au", "Ag", "Cu", "Al"])
def test_conductor_presets_agree_with_mitsuba_rgb(data_dir, material):
    """Our presets project the spectra to sRGB with an analytic fit of the CIE curves
    (tools/make_conductor_presets.py); Mitsuba uses tabulated CIE curves.  The IOR
    agrees to 2 % and the normal-incidence reflectance to 5e-3 (measured worst 2.5e-3, Cu)."""
    eta_m, k_m = mitsuba_ior(data_dir)[material]
    eta, k = fr.conductor_ior(material)
    one = torch.tensor(1.0, dtype=torch.float64)
    ours = fr.conductor(eta, k, one).numpy()
    ref = fr.conductor(eta_m, k_m, one).numpy()
    np.testing.assert_allclose(eta, eta_m, rtol=0.02)
    np.testing.assert_allclose(k, k_m, rtol=0.02)
    np.testing.assert_allclose(ours, ref, atol=5e-3)


def test_tutorial_exercises():
    """The worked examples of the chapter-9 tutorial (docs/references.md): GGX D and Schlick."""
    d = Distribution("ggx", 0.3, 0.3)
    th = math.radians(30.0)
    h = torch.tensor([math.sin(th), 0.0, math.cos(th)], dtype=torch.float64)
    assert d.D(h).item() == pytest.approx(0.284, abs=5e-4)
    f0 = fr.schlick_f0(1.5)
    assert f0 == pytest.approx(0.04, abs=1e-12)
    f = fr.schlick([f0] * 3, torch.tensor(math.cos(math.radians(60.0)), dtype=torch.float64))
    assert f[0].item() == pytest.approx(0.07, abs=5e-4)


# ----------------------------------------------------------------- Fresnel identities
COS = torch.linspace(0.0, 1.0, 101, dtype=torch.float64)


def test_dielectric_fresnel_identities():
    f = fr.dielectric(1.5, COS)
    assert f[-1, 0].item() == pytest.approx(0.04, abs=1e-12)  # ((n-1)/(n+1))^2
    assert f[0, 0].item() == pytest.approx(1.0, abs=1e-12)  # grazing
    # Total internal reflection from inside glass beyond the critical angle.
    inside = fr.dielectric(1 / 1.5, COS)
    crit = math.sqrt(1 - (1 / 1.5) ** 2)
    assert torch.all(inside[COS < crit - 1e-9] == 1.0)
    # A conductor with k = 0 is a dielectric.
    torch.testing.assert_close(fr.conductor(1.5, 0.0, COS), f, rtol=1e-10, atol=1e-12)


def test_thin_film_reduces_to_single_interfaces():
    # zero thickness: the film vanishes, leaving the substrate interface
    torch.testing.assert_close(
        fr.thin_film(1.33, 0.0, 1.5, COS), fr.dielectric(1.5, COS), rtol=1e-9, atol=1e-12
    )
    # film index equal to the substrate: one interface with the film's index
    torch.testing.assert_close(
        fr.thin_film(1.5, 321.0, 1.5, COS), fr.dielectric(1.5, COS), rtol=1e-9, atol=1e-12
    )


def test_thin_film_is_a_reflectance_and_iridescent():
    f = fr.thin_film(1.33, 400.0, 1.5, COS)
    assert torch.all((f >= 0) & (f <= 1))
    # interference: reflectance differs between channels and is not monotone in angle
    assert (f[-1].max() - f[-1].min()).item() > 0.01
    assert not torch.all(torch.diff(f[:, 1]) <= 0) and not torch.all(torch.diff(f[:, 1]) >= 0)


# ----------------------------------------------------------------- weak white furnace
@pytest.mark.parametrize("kind", ["ggx", "beckmann"])
@pytest.mark.parametrize("ax,ay", [(0.3, 0.3), (1.0, 1.0), (0.05, 0.6), (0.01, 0.01), (1e-4, 1e-4)])
def test_weak_white_furnace(kind, ax, ay):
    """int D(h) G1(wo) max(0, wo.h) / wo.n dh = 1, and int D cos = 1.

    Tolerance 1e-4: the quadrature resolves the anisotropic lobes at 88 deg to 2e-5."""
    d = Distribution(kind, ax, ay)
    th = np.radians([0.0, 30.0, 60.0, 80.0, 88.0])
    ph = np.radians([0.0, 45.0, 100.0])
    T, P = np.meshgrid(th, ph)
    wo = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    np.testing.assert_allclose(weak_white_furnace(d, wo), 1.0, atol=1e-4)
    assert projected_area(d) == pytest.approx(1.0, abs=1e-6)


def test_weak_white_furnace_detects_a_wrong_G1():
    """The check can fail: GGX D with the Beckmann G1 does not integrate to 1."""

    class Mixed(Distribution):
        def G1(self, w):
            return Distribution("beckmann", self.alpha_x, self.alpha_y).G1(w)

    wo = np.array([[math.sin(1.3), 0.0, math.cos(1.3)]])
    assert abs(weak_white_furnace(Mixed("ggx", 0.5, 0.5), wo)[0] - 1.0) > 1e-2


# ----------------------------------------------------------------- multiple scattering
@pytest.mark.parametrize("kind", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [0.1, 0.5, 1.0])
def test_kulla_conty_white_furnace(kind, alpha):
    """With F = 1 the compensated lobe reflects everything: rho = 1 to 1e-3 (mu >= 0.02)."""
    brdf = analytic.create("microfacet", distribution=kind, alpha=alpha, multiscatter=True)
    mu = np.array([0.02, 0.05, 0.1, 0.3, 0.6, 1.0])
    wi = np.stack([np.sqrt(1 - mu * mu), np.zeros_like(mu), mu], -1)
    rho = analytic.albedo(brdf, wi, n=16384)
    np.testing.assert_allclose(rho, 1.0, atol=1e-3)
    single = analytic.albedo(
        analytic.create("microfacet", distribution=kind, alpha=alpha), wi, n=16384
    )
    assert single.min() < 0.99  # there was energy to restore


def test_kulla_conty_with_fresnel_stays_below_one():
    brdf = analytic.create(
        "microfacet", alpha=0.8, multiscatter=True, fresnel="conductor", material="Au"
    )
    mu = np.linspace(0.02, 1.0, 12)
    wi = np.stack([np.sqrt(1 - mu * mu), np.zeros_like(mu), mu], -1)
    rho = analytic.albedo(brdf, wi, n=8192)
    single = analytic.albedo(
        analytic.create("microfacet", alpha=0.8, fresnel="conductor", material="Au"), wi, n=8192
    )
    assert np.all(rho <= 1.0 + 1e-3) and np.all(rho > single)

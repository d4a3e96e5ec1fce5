"""What the images determine (neural_brdf.inverse.determined).

* the posterior: each level's std is the diagonal of (J^T J / sigma^2 + I)^-1 computed
  here by a plain matrix inverse, the coarse levels' J^T J the block sums of the fine
  one's; the figures count a determined bin's observed fine bins only, so never more
  than the coverage;
* the estimate of J^T J from samples is unbiased: over many draws of simulated pixels
  that all mix the same bins in the same proportions (a rank-one truth), its mean is
  sum_p J_p^T J_p, while the plain product of the sampled rows is biased upwards;
* a flat rectangle under a constant environment: the coverage observes a band of the
  domain, but every pixel mixes it the same way, so no bin is determined at any
  resolution (the estimate without the correction would call some determined); the
  example's sphere under its sky determines far more than under a flash at the camera;
* the mask of determined pairs agrees with the map at the fine bins' centres, from the
  map and from its metrics.json summary;
* the command line: a config's images give the targets' noise; a bad reference file is
  one line and exit 2.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytestmark = pytest.mark.mitsuba

RES = 24


def test_each_levels_std_is_the_posterior_covariances_diagonal():
    from neural_brdf.inverse import determined as D

    rng = np.random.default_rng(0)
    n = D.FINE * D.FINE
    X = rng.random((3000, n)) * (rng.random((3000, n)) < 0.02)  # sparse rows
    X *= rng.random(n) < 0.5  # half the bins never seen
    F = X.T @ X
    sigma2 = 0.001
    energy = np.ones((D.FINE, D.FINE)) / n
    observed = rng.random((D.FINE, D.FINE)) < 0.7  # what the coverage observes
    fine_measure = D.coverage.bin_measure(D.FINE, 0.1)
    for bins in (D.FINE, 8):
        f = D.FINE // bins
        idx = np.arange(D.FINE)
        coarse = ((idx[:, None] // f) * bins + idx[None, :] // f).ravel()
        G = np.zeros((bins * bins, bins * bins))
        for a in range(n):  # the block sums, element by element
            G[coarse[a]] += np.bincount(coarse, weights=F[a], minlength=bins * bins)
        want = np.sqrt(np.diag(np.linalg.inv(G / sigma2 + np.eye(bins * bins))))
        lv = D._level(F, sigma2, bins, D.TOL, 0.1, energy, observed)
        assert np.allclose(lv.std.ravel(), want, rtol=1e-6, atol=1e-9)
        assert lv.determined.any() and not lv.determined.all()
        # counted over the observed fine bins of the determined ones, element by element
        counted = np.zeros((D.FINE, D.FINE), bool)
        for i in range(D.FINE):
            for j in range(D.FINE):
                counted[i, j] = observed[i, j] and want[coarse[i * D.FINE + j]] <= D.TOL
        counted &= fine_measure > 0
        assert np.array_equal(lv.fine, counted)
        assert lv.figure == pytest.approx(float(fine_measure[counted].sum()))
        assert lv.figure < float(lv.measure[lv.std <= D.TOL].sum())  # the unobserved parts
        assert lv.energy_figure == pytest.approx(float(energy[counted].sum()))


def test_the_information_estimate_is_unbiased_and_the_plain_product_is_not():
    from neural_brdf.inverse import determined as D

    rng = np.random.default_rng(1)
    bins, pixels, spp, c = 6, 40, 8, 2.0
    share = np.array([0.4, 0.3, 0.2, 0.1, 0.0, 0.0])  # every pixel mixes the same bins
    row_true = c * share / math.sqrt(c * c + 1e-2)  # J_p: the loss's weight of value c
    truth = pixels * np.outer(row_true, row_true)
    draws, plain = [], []
    for _ in range(400):
        col = rng.choice(bins, size=pixels * spp, p=share)
        row = np.repeat(np.arange(pixels), spp)
        draws.append(
            D.information(row, col, np.full(len(col), c), pixels=pixels, spp=spp, bins=bins)
        )
        S = np.zeros((pixels, bins))
        np.add.at(S, (row, col), c / spp)
        w = 1.0 / (S.sum(1) ** 2 + 1e-2)
        plain.append((S * w[:, None]).T @ S)
    mean, err = np.mean(draws, 0), np.std(draws, 0) / math.sqrt(len(draws))
    assert np.all(np.abs(mean - truth) <= 4 * err + 1e-12), np.abs(mean - truth) / (err + 1e-30)
    bias = np.diag(np.mean(plain, 0) - truth)[:4]
    assert np.all(bias > 10 * np.diag(err)[:4]), bias  # the sampled rows' own variance


@pytest.fixture(scope="module")
def plane(mi, tmp_path_factory):
    folder = tmp_path_factory.mktemp("plane")
    path = folder / "plane.xml"
    path.write_text(
        '<scene version="3.0.0">'
        '<sensor type="perspective"><float name="fov" value="20"/>'
        '<transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/>'
        "</transform>"
        f'<film type="hdrfilm"><integer name="width" value="{RES}"/>'
        f'<integer name="height" value="{RES}"/></film></sensor>'
        '<bsdf type="diffuse" id="fit"/><shape type="rectangle"><ref id="fit"/></shape>'
        '<emitter type="constant"><rgb name="radiance" value="1"/></emitter></scene>'
    )
    return path


def test_a_plane_under_a_constant_sky_is_observed_but_determines_nothing(plane):
    from neural_brdf.inverse import coverage
    from neural_brdf.inverse import determined as D

    observed = coverage.compute([plane], rays=RES * RES * 12).figure
    det = D.compute([plane], None, None, spp=64)
    assert observed > 0.15
    assert all(lv.figure == 0.0 for lv in det.levels.values()), det.levels
    assert D.warning(det) is not None and "reflected light of the diffuse start" in D.warning(det)


def test_a_sky_determines_more_than_a_flash(mi, tmp_path):
    from neural_brdf.inverse import coverage
    from neural_brdf.inverse import determined as D
    from neural_brdf.inverse import scene as example

    example.write_exr(tmp_path / "sky.exr", example.sky(32))
    figures = {}
    for capture in ("environment", "flash"):
        paths = []
        for k, (az, el) in enumerate(example.VIEWS[:3]):
            path = tmp_path / f"{capture}{k + 1}.xml"
            emitters = example.capture_emitters(capture, k)
            path.write_text(example.scene_xml(az, el, resolution=RES, emitters=emitters))
            paths.append(path)
        det = D.compute(paths, None, None, spp=64)
        figures[capture] = {b: lv.figure for b, lv in det.levels.items()}
        # within what the coverage observes (computed here: the same views and seed)
        cov = coverage.compute(paths, seed=0)
        assert np.array_equal(det.observed, cov.observed)
        for lv in det.levels.values():
            assert not (lv.fine & ~cov.observed).any() and lv.figure <= cov.figure + 1e-12
        # the mask agrees with the map at the fine bins' centres (phi_d = pi / 2: in the
        # domain)
        from neural_brdf.measured import merl

        b = D.FINE
        centre = (np.arange(b) + 0.5) * (0.5 * math.pi / b)
        th, td = np.meshgrid(centre, centre, indexing="ij")
        wi, wo = merl.directions(th.ravel(), 0.0, td.ravel(), 0.5 * math.pi)
        wi, wo = np.asarray(wi), np.asarray(wo)
        inside = (wi[:, 2] > det.min_cos) & (wo[:, 2] > det.min_cos)
        mask = D.determined_mask(det, wi, wo)
        assert np.array_equal(mask, inside & det.level.fine.ravel())
        assert np.array_equal(D.summary_mask(D.summary(det), wi, wo), mask)
    assert figures["environment"][8] > 2 * figures["flash"][8] > 0, figures
    assert figures["environment"][4] > 0.5, figures


def test_the_command_line_reads_a_configs_noise_and_refuses_a_bad_reference(mi, tmp_path, capsys):
    from neural_brdf.inverse import determined as D
    from neural_brdf.inverse import scene as example

    example.write(tmp_path, resolution=RES, spp=16, steps=1)
    out = tmp_path / "det.json"
    picture = tmp_path / "det.png"
    assert D.main([str(tmp_path / "fit.yaml"), "--json", str(out), "-o", str(picture)]) == 0
    info = json.loads(out.read_text())
    assert info["noise_source"] == "targets" and info["noise"] != D.NOMINAL_NOISE
    assert info["picture"] == "det.png" and picture.read_bytes()[:4] == b"\x89PNG"
    assert sum(info["pixels_sampled"]) > 0
    capsys.readouterr()
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene/>")
    assert D.main([str(tmp_path / "fit.yaml"), "--reference", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.xml" in err[0] and "<bsdf>" in err[0], err
    # a <bsdf> of a plugin Mitsuba has not: a RuntimeError's traceback before
    bad.write_text('<bsdf type="foo"/>')
    assert D.main([str(tmp_path / "fit.yaml"), "--reference", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.xml" in err[0] and "Mitsuba cannot load it" in err[0], err
    # an output in no folder: said before the work (a FileNotFoundError after it before)
    missing = tmp_path / "missing" / "d.png"
    assert D.main([str(tmp_path / "fit.yaml"), "-o", str(missing)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no folder" in err[0], err
    # the views held out whole (images.validation_views) are not fitted: not counted
    held = tmp_path / "held.yaml"
    held.write_text((tmp_path / "fit.yaml").read_text() + "\nimages:\n  validation_views: [1]\n")
    every, _ = D._inputs([str(tmp_path / "fit.yaml")])
    fitted, _ = D._inputs([str(held)])
    assert [v.scene_path for v in fitted] == [every[0].scene_path, every[2].scene_path]

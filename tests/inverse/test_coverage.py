"""What the images determine (neural_brdf.inverse.coverage), llvm_ad_rgb.

* a co-located flash (a point light at each camera) observes only wi = wo: all its
  weight falls in the first theta_d bin, while the example's environment covers far
  more of the (theta_h, theta_d) domain; the warning fires for the first only;
* the coverage figure never shrinks when a view is added, whatever its lighting;
* every sample kept has both cosines > 0, and its wo and wi are the directions from the
  hit point to the camera and to the light, as computed here from the hit point and the
  scene's own positions;
* independently of the module's sampling: with a point light and a camera at known
  positions around the unit sphere, the pair at the film's centre pixel (an odd film,
  pixel centres) is the analytic one (wo the normal, cos theta_i from the light's
  position, theta_h = theta_d = theta_i / 2) with the analytic weight I / r^2 cos theta_i;
* the bins' domain measure equals a histogram of uniformly drawn pairs.

The scenes are written here (neural_brdf.inverse.scene) with 24 x 24 films and a few
thousand rays per view; the file takes a few seconds.
"""

from __future__ import annotations

import contextlib
import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.mitsuba

RES = 24
RAYS = RES * RES * 12  # camera rays per view


@pytest.fixture(scope="module")
def scenes(mi, tmp_path_factory) -> dict[str, list[Path]]:
    """capture -> the example's three view scenes lit that way (no target images)."""
    from neural_brdf.inverse import scene as example

    folder = tmp_path_factory.mktemp("coverage")
    example.write_exr(folder / "sky.exr", example.sky(32))
    out: dict[str, list[Path]] = {}
    for capture in example.CAPTURES:
        out[capture] = []
        for k, (az, el) in enumerate(example.VIEWS[:3]):
            path = folder / f"{capture}{k + 1}.xml"
            emitters = example.capture_emitters(capture, k)
            path.write_text(example.scene_xml(az, el, resolution=RES, emitters=emitters))
            out[capture].append(path)
    return out


def _coverage(paths, **kwargs):
    from neural_brdf.inverse import coverage

    return coverage.compute(paths, rays=RAYS, **kwargs)


# ------------------------------------------------------------------ flash vs environment
def test_flash_observes_only_theta_d_zero_and_an_environment_far_more(scenes, tmp_path):
    from neural_brdf.inverse import coverage

    flash = _coverage(scenes["flash"])
    env = _coverage(scenes["environment"])
    for cov in (flash, env):
        assert all(v.pixels_lit > 0.4 * v.pixels for v in cov.views)
    weight = sum(v.weight for v in flash.views)
    assert weight.sum() > 0
    assert weight[:, 0].sum() / weight.sum() > 0.999  # theta_d in [0, 2.8 degrees)
    _, theta_d, _ = coverage.half_diff(flash.wi, flash.wo)
    assert np.degrees(theta_d).max() < 0.5
    assert not flash.observed[:, 1:].any()
    assert flash.figure < 0.02
    # the environment: most of the domain, many theta_d rows
    assert env.figure > 0.5
    assert env.figure > 20 * flash.figure
    assert env.observed.any(0).sum() > 20
    assert coverage.warning(flash) is not None and coverage.warning(env) is None
    # a flash pixel pins (nearly) one bin; an environment pixel mixes many
    assert coverage.mixing(flash) < 4 < 20 < coverage.mixing(env)
    # metrics.json's part and the picture
    info = json.loads(json.dumps(coverage.summary(flash)))
    assert info["figure"] == round(flash.figure, 4)
    assert info["theta_d_observed_deg"] == [0.0, 90.0 / coverage.BINS]
    assert len(info["per_view"]) == 3
    png = coverage.write_picture(env, tmp_path / "coverage.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_flash_beside_the_environment_lights_with_both(mi, scenes):
    # scene_xml's ``beside``: the environment stays and the flash is added, so the view
    # observes the flash's theta_d = 0 row and the environment's many rows
    from neural_brdf.inverse import scene as example

    env_view = scenes["environment"][0]
    az, el = example.VIEWS[0]
    path = env_view.with_name("environment_flash1.xml")
    flash = example.capture_emitters("flash", 0)
    path.write_text(example.scene_xml(az, el, resolution=RES, beside=flash))
    kinds = [e.get("type") for e in ET.parse(path).getroot().iter("emitter")]
    assert kinds == ["envmap", "point"], kinds
    assert len(mi.load_file(str(path)).emitters()) == 2
    both, alone = _coverage([path]), _coverage([scenes["flash"][0]])
    assert both.observed[:, 0].any() and both.observed.any(0).sum() > 20
    assert not alone.observed[:, 1:].any()


# ------------------------------------------------------------------ views added
def test_coverage_never_shrinks_when_views_are_added(scenes):
    order = [
        scenes["environment"][0],
        scenes["flash"][0],
        scenes["lights"][0],
        scenes["lights"][2],
        scenes["environment"][2],
    ]
    figures, observed = [], []
    for n in range(1, len(order) + 1):
        cov = _coverage(order[:n])
        figures.append(cov.figure)
        observed.append(cov.observed)
    for k in range(1, len(order)):
        assert figures[k] >= figures[k - 1], figures
        assert not (observed[k - 1] & ~observed[k]).any(), f"a bin lost at view {k + 1}"
    lights = [_coverage(scenes["lights"][: n + 1]).figure for n in range(3)]
    assert lights[0] < lights[1] < lights[2], lights  # each light adds theta_d rows
    # views that add weight elsewhere (flashes: theta_d = 0) take nothing away
    band = _coverage(scenes["lights"][:1])
    more = _coverage(scenes["lights"][:1] + scenes["flash"])
    assert not (band.observed & ~more.observed).any()
    assert more.figure > band.figure


# ------------------------------------------------------------------ the pairs
def test_pairs_are_above_the_surface_and_point_at_camera_and_light(mi, scenes):
    from neural_brdf.inverse import coverage
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene as example

    cov = _coverage(scenes["lights"] + scenes["flash"])
    assert len(cov.wi) > 1000
    assert (cov.wi[:, 2] > 0).all() and (cov.wo[:, 2] > 0).all()
    assert np.allclose(np.linalg.norm(cov.wi, axis=1), 1, atol=1e-4)
    assert np.allclose(np.linalg.norm(cov.wo, axis=1), 1, atol=1e-4)
    assert np.array_equal(cov.pair_observed, coverage.observed_mask(cov, cov.wi, cov.wo))

    for k in (0, 2):  # point lights: LIGHTS[0] and LIGHTS[2]
        path = scenes["lights"][k]
        tree, _ = inverse.read_scene(path, "test")
        s = coverage.view_samples(coverage.load(path, tree), spp=4, seed=k)
        lit = s.weight > 0
        assert lit.sum() > 50
        camera = np.array(example.camera_origin(*example.VIEWS[k]))
        _, az, el = example.LIGHTS[k][0]
        light = example.LIGHT_DISTANCE * np.array(example.direction(az, el))
        p, n = s.position[lit], s.normal[lit]
        to_cam = camera - p
        to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
        to_light = light - p
        to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
        np.testing.assert_allclose(s.wo[lit, 2], np.sum(n * to_cam, 1), atol=2e-4)
        np.testing.assert_allclose(s.wi[lit, 2], np.sum(n * to_light, 1), atol=2e-4)
        np.testing.assert_allclose(
            np.sum(s.wi[lit] * s.wo[lit], 1), np.sum(to_cam * to_light, 1), atol=2e-4
        )
        np.testing.assert_allclose(np.linalg.norm(n - p, axis=1), 0, atol=1e-4)  # unit sphere
        # unlit samples: the light is behind the surface (the sphere shadows itself)
        assert (np.sum(s.normal[~lit] * (light - s.position[~lit]), 1) < 1e-3).all()


def test_occluded_light_samples_weigh_nothing(mi, scenes, tmp_path):
    """A small sphere between the light and the fitted one: the samples whose segment to
    the light crosses it (computed here) have weight 0, all others facing it weigh."""
    from neural_brdf.inverse import coverage
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene as example

    _, az, el = example.LIGHTS[0][0]
    light = example.LIGHT_DISTANCE * np.array(example.direction(az, el))
    centre, radius = 0.4 * light, 0.5
    blocker = (
        f'<shape type="sphere"><point name="center" value="{centre[0]:.6f}, '
        f'{centre[1]:.6f}, {centre[2]:.6f}"/><float name="radius" value="{radius}"/></shape>'
    )
    path = tmp_path / "blocked.xml"
    path.write_text(scenes["lights"][0].read_text().replace("</scene>", blocker + "</scene>"))
    tree, _ = inverse.read_scene(path, "test")
    s = coverage.view_samples(coverage.load(path, tree), spp=4, seed=1)
    p = s.position
    d = light - p
    length = np.linalg.norm(d, axis=1)
    d /= length[:, None]
    # the segment p -> light against the blocker: |p + t d - c| = r for t in (0, length)
    oc = p - centre
    b = np.sum(oc * d, 1)
    disc = b * b - (np.sum(oc * oc, 1) - radius**2)
    t_near = -b - np.sqrt(np.maximum(disc, 0))
    blocked = (disc > 0) & (t_near > 0) & (t_near < length)
    facing = np.sum(s.normal * d, 1) > 1e-3
    margin = np.abs(disc) > 1e-3  # leave out grazing the blocker's silhouette
    assert (facing & blocked & margin).sum() > 30
    assert (s.weight[facing & blocked & margin] == 0).all()
    assert (s.weight[facing & ~blocked & margin] > 0).all()


# ------------------------------------------------------------------ an analytic pair
@pytest.mark.parametrize(
    "camera, light",
    [((0.0, 0.0), (50.0, 20.0)), ((140.0, 30.0), (100.0, -10.0)), ((250.0, -20.0), (250.0, 50.0))],
)
def test_centre_pixel_pair_is_the_analytic_one(mi, tmp_path, camera, light):
    from neural_brdf.inverse import coverage
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene as example

    intensity, distance = 20.0, 5.0
    lpos = distance * np.array(example.direction(*light))
    xml = example.scene_xml(
        *camera, resolution=25, emitters=example.point_light(list(lpos), intensity)
    )
    path = tmp_path / "view.xml"
    path.write_text(xml)
    tree, _ = inverse.read_scene(path, "test")
    s = coverage.view_samples(coverage.load(path, tree), spp=1, jitter=False)
    centre = s.pixel == 12 * 25 + 12
    assert centre.sum() == 1
    # the analytic pair: the ray through the film's centre meets the unit sphere at its
    # point p facing the camera, whose normal is the direction to the camera
    n = np.array(example.direction(*camera))
    to_light = lpos - n
    r2 = float(to_light @ to_light)
    cos_i = float(n @ to_light) / math.sqrt(r2)
    wi, wo = s.wi[centre][0], s.wo[centre][0]
    np.testing.assert_allclose(s.position[centre][0], n, atol=1e-4)
    np.testing.assert_allclose(wo, [0.0, 0.0, 1.0], atol=1e-4)
    np.testing.assert_allclose(wi[2], cos_i, atol=1e-4)
    np.testing.assert_allclose(np.hypot(wi[0], wi[1]), math.sqrt(1 - cos_i**2), atol=1e-4)
    theta_h, theta_d, _ = coverage.half_diff(wi[None], wo[None])
    np.testing.assert_allclose([theta_h[0], theta_d[0]], [0.5 * math.acos(cos_i)] * 2, atol=1e-3)
    np.testing.assert_allclose(s.weight[centre][0], intensity / r2 * cos_i, rtol=1e-4)


# ------------------------------------------------------------------ the measure
def test_bin_measure_is_the_measure_of_uniform_pairs():
    from neural_brdf.inverse import coverage

    bins, c = 8, coverage.MIN_COS
    m = coverage.bin_measure(bins, c)
    rng = np.random.default_rng(3)

    def hemisphere(n):  # uniform in solid angle
        z = rng.random(n)
        phi = 2 * math.pi * rng.random(n)
        s = np.sqrt(1 - z * z)
        return np.stack([s * np.cos(phi), s * np.sin(phi), z], -1)

    wi, wo = hemisphere(400_000), hemisphere(400_000)
    keep = (wi[:, 2] > c) & (wo[:, 2] > c)
    th, td, _ = coverage.half_diff(wi[keep], wo[keep])
    hist = np.zeros((bins, bins))
    np.add.at(hist, (coverage.bin_index(th, bins), coverage.bin_index(td, bins)), 1.0)
    hist /= hist.sum()
    assert m.sum() == pytest.approx(1.0)
    assert np.abs(hist - m).max() < 2e-3
    big = m > 5e-3
    assert np.abs(hist[big] / m[big] - 1).max() < 0.06


def test_the_map_paints_nothing_beyond_the_domains_edge():
    """Every bin the edge cos(theta_h) cos(theta_d) = min_cos crosses is drawn (all
    observed here): its part beyond the edge is white in the rendered map, its part
    inside keeps its colour."""
    from neural_brdf.inverse import coverage

    bins, c = 32, coverage.MIN_COS
    m = coverage.bin_measure(bins, c)
    inside = m > 0
    cov = coverage.Coverage(
        views=[], bins=bins, min_cos=c, threshold=0.05, rays=0, seed=0, measure=m,
        density=np.where(inside, 1.0, 0.0), observed=inside, figure=1.0,
        wi=np.zeros((0, 3), np.float32), wo=np.zeros((0, 3), np.float32),
        pair_share=np.zeros(0, np.float32), pair_view=np.zeros(0, int),
        pair_observed=np.zeros(0, bool), pairs_total=0,
    )  # fmt: skip
    fig = coverage.map_figure(cov)
    fig.set_dpi(400)  # a bin some 40 pixels wide
    fig.canvas.draw()
    rgba = np.asarray(fig.canvas.buffer_rgba())
    ax = fig.axes[0]
    width = 90.0 / bins
    crossed = beyond_checked = 0
    for i in range(bins):
        for j in range(bins):
            th = np.radians(width * (i + np.array([0.15, 0.85])))
            td = np.radians(width * (j + np.array([0.15, 0.85])))
            lo = math.cos(th[1]) * math.cos(td[1])
            hi = math.cos(th[0]) * math.cos(td[0])
            if not (inside[i, j] and lo < c - 0.006 and hi > c + 0.006):
                continue
            crossed += 1
            # the bin's corner beyond the edge, and the one inside
            for (a, b), want_white in (((th[1], td[1]), True), ((th[0], td[0]), False)):
                x, y = ax.transData.transform((np.degrees(a), np.degrees(b)))
                px = rgba[int(round(rgba.shape[0] - y)), int(round(x)), :3]
                assert bool((px > 250).all()) == want_white, (i, j, want_white, px)
                beyond_checked += want_white
    assert crossed >= 10 and beyond_checked == crossed


@pytest.mark.parametrize(
    "cut, needle",
    [(r"<emitter .*?</emitter>", "no emitter"), (r"<sensor .*?</sensor>", "no <sensor>")],
    ids=["no emitter", "no sensor"],
)
def test_a_scene_without_light_or_camera_is_one_line_and_exit_2(
    scenes, tmp_path, capsys, cut, needle
):
    # the check a fit makes before its start (a traceback from the rays' sampling before)
    import re

    from neural_brdf.inverse import coverage

    text = scenes["lights"][0].read_text()
    edited = tmp_path / "edited.xml"
    edited.write_text(re.sub(cut, "", text, flags=re.S))
    assert edited.read_text() != text
    code = coverage.main([str(edited)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "edited.xml" in err and needle in err, err


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--rays", "0"], "--rays: must be >= 1"),
        (["--variant", "scalar_rgb"], "needs a vectorised RGB variant"),
        (["--json", "{missing}/x.json"], "cannot write (no folder"),
        (["-o", "{missing}/c.png"], "cannot write (no folder"),
        (["--json", "{here}/c.json/"], "a folder's name"),
        (["-o", "{here}/c.png/"], "a folder's name"),
    ],
    ids=["rays 0", "scalar variant", "json in no folder", "picture in no folder", "json/", "png/"],
)
def test_the_command_line_refuses_bad_options_in_one_line(scenes, tmp_path, capsys, args, needle):
    """--rays 0 ran with another figure (93.8 % for 100 %), a scalar variant and an
    output in a missing folder ended in tracebacks, after the work for the last."""
    from neural_brdf.inverse import coverage

    args = [a.format(missing=tmp_path / "missing", here=tmp_path) for a in args]
    with pytest.raises(SystemExit) if args[0] == "--rays" else contextlib.nullcontext():
        code = coverage.main([str(scenes["lights"][0]), *args])
        assert code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and needle in err, err
    assert not (tmp_path / "c.png").exists() and not (tmp_path / "c.json").exists()


def test_a_config_s_views_held_out_whole_are_not_counted(scenes, tmp_path, capsys):
    """The fit leaves the views of images.validation_views out of its coverage; the
    command counted them (40.6 % with no warning for the 13.3 % the fit sees)."""
    from neural_brdf.inverse import coverage

    views = scenes["lights"]
    entries = "".join(f"    - {{scene: {v}, image: {v.with_suffix('.exr')}}}\n" for v in views)
    cfg = tmp_path / "fit.yaml"
    cfg.write_text(f"target:\n  images:\n{entries}images:\n  validation_views: [1]\n")
    assert coverage._scenes([str(cfg)]) == [views[0], views[2]]
    assert "held out whole" in capsys.readouterr().err


def test_a_share_below_one_never_reads_as_100_percent():
    from neural_brdf.inverse.coverage import percent_text

    assert percent_text(0.9995) == "99.95" and percent_text(0.99999) == "99.99"
    assert percent_text(1.0) == "100.0" and percent_text(0.406) == "40.6"

"""The starts of an images fit (neural_brdf.inverse.starts), llvm_ad_rgb.

* the choice: three views (24 x 24, 16 spp targets) of a ``diffuse``, a ``roughplastic``
  and a copper ``roughconductor`` sphere; the family chosen by the held-out pixels is
  the true one's (or one at least as good there, or a simpler one within the rule's tie:
  a metallic ``principled`` for the copper), and the true family's fitted key
  parameters are close to the truth (roughness within 30 %, reflectance within 10 %);
* the choice never sees the truth: every scene's ``<bsdf id="fit">`` is replaced, after
  its target was rendered, by a BSDF of another family, and ``choose_start`` takes the
  views alone;
* the split: the held-out pixels are disjoint from the training pixels, together they
  are the object's pixels, and the seed decides them;
* the ranges: every free variable, however large, gives parameters in their ranges (a
  property test), the conductor's eta and k give back its F0, and Mitsuba evaluates
  every such BSDF to finite, non-negative values; the principled's metallic reaches 0
  and 1 in a few dozen steps of Adam's size;
* the teacher: ``teacher_xml`` read by ``MitsubaTarget`` evaluates as the element does;
  ``distill`` trains a network on it in a run folder that holds the file.

About a minute and a half on 2 cores (the choices are ``slow``).
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from neural_brdf import config
from neural_brdf.inverse import families

pytestmark = pytest.mark.mitsuba

RES = 24  # film size of the test views
TARGET_SPP = 16
ALPHA_TOL = 0.30  # relative error of a fitted roughness
REFLECTANCE_TOL = 0.10  # ... of a fitted reflectance (each channel)


def _truths():
    from neural_brdf.inverse import fit as inverse

    return {
        "diffuse": inverse.bsdf_element("diffuse", reflectance=(0.6, 0.45, 0.3)),
        "roughplastic": inverse.bsdf_element(
            "roughplastic",
            distribution="ggx",
            alpha=0.15,
            diffuse_reflectance=(0.5, 0.2, 0.1),
            int_ior=1.5,
        ),
        "roughconductor": inverse.bsdf_element(
            "roughconductor", distribution="ggx", alpha=0.2, material="Cu"
        ),
    }


# after its targets are rendered, each scene gets a BSDF of another family
DECOYS = {"diffuse": "roughconductor", "roughplastic": "diffuse", "roughconductor": "roughplastic"}


# ------------------------------------------------------------------ fixtures
def write_material(
    folder: Path, truth: ET.Element, decoy: ET.Element, res: int = RES, spp: int = TARGET_SPP
) -> Path:
    """The example's three views (``res``², ``spp`` samples) with ``truth`` as the
    material of the targets, then ``decoy`` in the scenes in its place; returns fit.yaml."""
    from neural_brdf.fileio import atomic_write
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import scene

    scene.write(folder, resolution=res, spp=spp)
    for k in (1, 2, 3):
        xml = folder / f"view{k}.xml"
        atomic_write(xml, inverse.scene_text(ET.parse(xml), truth))
        scene.write_exr(folder / f"view{k}.exr", scene.render_file(xml, spp, seed=k))
        atomic_write(xml, inverse.scene_text(ET.parse(xml), decoy))
    return folder / "fit.yaml"


@pytest.fixture(scope="module")
def materials(mi, tmp_path_factory) -> dict[str, Path]:

    out = {}
    for name, truth in _truths().items():
        fam = families.FAMILIES[DECOYS[name]]
        decoy = fam.element(fam.numbers(fam.free_of(fam.initial())))
        out[name] = write_material(tmp_path_factory.mktemp(name), truth, decoy)
    return out


def views_of(path: Path):
    from neural_brdf.inverse import fit as inverse

    return inverse.read_views(config.load(path))


def truth_figures(name: str, mi) -> dict[str, np.ndarray]:
    """The truth's key parameters, read from its Mitsuba BSDF (tests only)."""
    from neural_brdf.inverse import fit as inverse

    params = mi.traverse(inverse.mitsuba_bsdf(_truths()[name]))

    def get(key):
        return np.asarray(params[key], dtype=np.float64).reshape(-1)

    if name == "diffuse":
        return {"reflectance": get("reflectance.value")}
    if name == "roughplastic":
        return {"diffuse_reflectance": get("diffuse_reflectance.value"), "alpha": get("alpha")}
    return {
        "alpha": get("alpha.value"),
        "f0": families.conductor_f0(get("eta.value"), get("k.value")),
    }


def relative_error(fitted, truth) -> float:
    f = np.asarray(fitted, dtype=np.float64).reshape(-1)
    return float(np.max(np.abs(f - truth) / np.abs(truth)))


# ------------------------------------------------------------------ the choice
@pytest.mark.slow
@pytest.mark.parametrize("name", ["diffuse", "roughplastic", "roughconductor"])
def test_choice_finds_the_family_and_its_parameters(mi, materials, name):
    from neural_brdf.inverse import starts

    views = views_of(materials[name])
    choice = starts.choose_start(views, seed=3)  # the default schedule
    by_family = {c.family: c for c in choice.candidates}
    true = by_family[name]
    # the true family, or one at least as good there, or a simpler one the rule ties with
    # the best (within its noise and never more than TIE_MAX worse): a metallic
    # principled can stand in for a copper conductor
    chosen = choice.chosen
    assert (
        choice.family == name
        or chosen.val_loss <= true.val_loss
        or (
            choice.margins[choice.family]["tied"]
            and chosen.complexity < true.complexity
            and chosen.val_loss <= (1.0 + starts.TIE_MAX) * true.val_loss
        )
    ), choice.summary()
    # the held-out figure tells the families apart: each of the three that cannot hold
    # the truth does worse than the true one there
    for c in choice.candidates:
        if c.family in ("diffuse", "roughplastic", "roughconductor") and c.family != name:
            assert c.val_loss > true.val_loss, (c.family, choice.margins)
    for key, value in truth_figures(name, mi).items():
        tol = ALPHA_TOL if key == "alpha" else REFLECTANCE_TOL
        err = relative_error(true.params[key], value)
        assert err <= tol, f"{name}: {key} {true.params[key]} against {value} ({err:.1%})"
    summary = choice.summary()
    assert summary["family"] == choice.family
    assert [c["family"] for c in summary["candidates"]] == list(families.DEFAULT)
    assert all(math.isfinite(c["val_loss"]) for c in summary["candidates"])


@pytest.mark.slow
def test_a_clear_coat_is_found_and_a_bare_principled_keeps_its_simpler_family(mi, tmp_path):
    """Views of a principled under a clear coat: the clearcoat family, started from the
    fitted principled (warm_start), wins the choice over it by the held-out pixels and
    finds the coat; views of the same material without a coat tie the two, and the rule
    gives the tie to the principled (fewer free scalars)."""
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import starts

    base = {"base_color": (0.05, 0.1, 0.2), "metallic": 0.0, "roughness": 0.6, "specular": 0.5}
    decoy = inverse.bsdf_element("diffuse", reflectance=0.5)
    chosen = {}
    for coat in (1.0, 0.0):
        truth = inverse.bsdf_element("principled", **base, clearcoat=coat, clearcoat_gloss=0.6)
        # a coat is a faint lobe (a quarter of an IOR 1.5 Fresnel): finer, cleaner views
        path = write_material(tmp_path / f"coat{coat:g}", truth, decoy, res=32, spp=32)
        choice = starts.choose_start(views_of(path), ["principled", "clearcoat"], seed=3)
        by = {c.family: c for c in choice.candidates}
        chosen[coat] = (choice.family, by["clearcoat"].params, by, choice.margins)
    family, params, by, margins = chosen[1.0]
    assert family == "clearcoat", margins
    assert by["clearcoat"].val_loss < 0.9 * by["principled"].val_loss, margins
    assert float(np.ravel(params["clearcoat"])[0]) > 0.4, params
    family, params, by, margins = chosen[0.0]
    assert family == "principled", margins
    assert margins["clearcoat"]["tied"], margins


def test_fit_start_on_the_training_pixels(mi, materials):
    """fit_start's four results; from a start far off, the fit on the training pixels
    recovers the reflectance and lowers the loss on the held-out ones."""
    from neural_brdf.inverse import starts

    views = views_of(materials["diffuse"])
    train, held = starts.split_pixels(views, 0.3, seed=1)
    far = {"reflectance": [0.2, 0.2, 0.2]}
    kw = {"seed": 1, "mask_train": train, "mask_val": held, "init": far}
    element, params, train_loss, val_loss = starts.fit_start(views, "diffuse", steps=60, **kw)
    assert element.get("type") == "diffuse"
    assert relative_error(params["reflectance"], [0.6, 0.45, 0.3]) <= REFLECTANCE_TOL
    # the views are left loaded with the fitted BSDF: the same figure again, by the
    # function the network stage can use (same seeds, same samples)
    again = starts.noise_free_loss(views, held, spp=starts.Schedule().val_spp, seed=1)
    assert again == pytest.approx(val_loss, rel=1e-6)
    plain = starts.noise_free_loss(views, held, spp=starts.Schedule().val_spp, seed=1, plain=True)
    assert plain > val_loss  # the render's own noise, which the noise-free figure leaves out
    _, start, start_train, start_val = starts.fit_start(views, "diffuse", steps=0, **kw)
    assert np.allclose(start["reflectance"], 0.2, rtol=1e-3)
    assert 0 < val_loss < start_val / 5 and 0 < train_loss < start_train / 5


def test_the_choice_takes_the_views_alone():
    from neural_brdf.inverse import starts

    params = inspect.signature(starts.choose_start).parameters
    assert next(iter(params)) == "views"
    for p in params.values():
        assert p.name == "views" or p.kind is inspect.Parameter.KEYWORD_ONLY or p.name == "families"
    assert not {"truth", "bsdf", "element", "reference"} & set(params)


def test_no_held_out_pixels_is_refused(mi, materials):
    from neural_brdf.inverse import starts

    views = views_of(materials["diffuse"])
    with pytest.raises(ValueError, match="no held-out pixels"):
        starts.choose_start(views, ["diffuse"], steps=1, val_share=0.0)
    with pytest.raises(ValueError, match="start family 'plaster'"):
        starts.choose_start(views, ["plaster"], steps=1)


# ------------------------------------------------------------------ the split
def test_split_is_disjoint_covers_the_object_and_follows_the_seed(mi, materials):
    from neural_brdf.inverse import starts

    views = views_of(materials["roughconductor"])
    train, held = starts.split_pixels(views, 0.25, seed=5)
    again = starts.split_pixels(views, 0.25, seed=5)
    other = starts.split_pixels(views, 0.25, seed=6)
    for i, v in enumerate(views):
        obj = starts.object_mask(v)
        assert obj.sum() > 100
        assert not (train[i] & held[i]).any()
        assert np.array_equal(train[i] | held[i], obj)
        share = held[i].sum() / obj.sum()
        assert 0.1 < share < 0.4, share
        assert np.array_equal(held[i], again[1][i])
    assert any(not np.array_equal(h, o) for h, o in zip(held, other[1], strict=True))
    # whole tiles: a held-out pixel's tile holds no training pixel
    for tr, he in zip(train, held, strict=True):
        t = starts.tiles(he.shape, 4)
        assert not np.intersect1d(t[tr], t[he]).size


def test_split_leaves_out_the_runs_own_validation_split(mi, materials):
    """Pixels and views the run holds out (images.validation_*: fit.split_views) are in
    neither part of the choice's split."""
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import starts

    views = views_of(materials["roughconductor"])
    inverse.split_views(views, config.Images(validation_pixels=0.2, validation_views=[2]), seed=0)
    train, held = starts.split_pixels(views, 0.25, seed=5)
    for i, v in enumerate(views):
        reserved = v.validation_mask()
        assert reserved is not None and reserved.any()
        assert not (train[i] & reserved).any() and not (held[i] & reserved).any()
    assert train[0].any() and held[0].any()
    assert not train[2].any() and not held[2].any()  # the view held out whole


def test_object_mask_ignores_the_scenes_bsdf(mi, materials):
    """The mask comes from the geometry: the same with any BSDF in the scene."""
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import starts

    a = views_of(materials["diffuse"])[0]
    b = views_of(materials["roughplastic"])[0]
    assert inverse.fit_element(a.tree).get("type") != inverse.fit_element(b.tree).get("type")
    assert np.array_equal(starts.object_mask(a), starts.object_mask(b))


# ------------------------------------------------------------------ the ranges
FREE = st.floats(-1e6, 1e6, allow_nan=False) | st.sampled_from([-1e30, -80.0, 0.0, 80.0, 1e30])


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_every_free_variable_gives_parameters_in_range(data):

    fam = families.FAMILIES[data.draw(st.sampled_from(sorted(families.FAMILIES)))]
    free = {
        n: np.array(data.draw(st.lists(FREE, min_size=p.channels, max_size=p.channels)))
        for n, p in fam.params.items()
    }
    values = fam.values(free, np)
    for n, p in fam.params.items():
        v = values[n]
        assert np.all(np.isfinite(v)) and np.all(v >= p.bound.lo) and np.all(v <= p.bound.hi)
    for n in ("reflectance", "diffuse_reflectance", "f0", "weight"):
        if n in values:
            assert np.all(values[n] <= 1.0)
    if "f0" in values:
        eta, k = families.eta_k(values["f0"], values["edge_tint"], np)
        assert np.all(np.isfinite(eta)) and np.all(eta > 0) and np.all(np.isfinite(k))
        assert np.allclose(families.conductor_f0(eta, k), values["f0"], rtol=1e-6, atol=1e-9)
    # free_of inverts values (up to its clamp, 1e-4 of the range inside either end)
    back = fam.values(fam.free_of(values), np)
    for n, p in fam.params.items():
        b = p.bound
        t = np.log if b.log else np.asarray
        span = t(b.hi) - t(b.lo)
        assert np.all(np.abs(t(back[n]) - t(values[n])) <= 1.01e-4 * span + 1e-12)


def test_the_principled_metallic_reaches_a_dielectric_and_a_metal():
    """Most real materials have a metallic of 0 or 1.  Adam steps its free variable by
    about the rate per step; at 0.02 a step (the refinement's), the principled's
    metallic goes from its start to within 1e-3 of either end in at most 60 steps (the
    logistic map needs 300 to 390: a dielectric fitted as metallic 0.05 to 0.1)."""

    b = families.FAMILIES["principled"].params["metallic"].bound
    assert float(b.value(np.array(0.0), np)) == 0.0
    assert float(b.value(np.array(math.pi / 2), np)) == 1.0
    for end, sign in ((0.0, -1.0), (1.0, 1.0)):
        z = float(b.free(np.array(families.METALLIC_START)))
        steps = 0
        while abs(float(b.value(np.array(z), np)) - end) > 1e-3 and steps < 1000:
            z += sign * 0.02
            steps += 1
        assert steps <= 60, (end, steps)


@settings(max_examples=30, deadline=None)
@given(data=st.data())
def test_mitsuba_gets_valid_parameters_for_any_free_variable(mi, data):
    """The same maps in Dr.Jit (float32, as the fit steps them): parameters in range,
    and the BSDF Mitsuba builds from them is finite and non-negative."""
    import drjit as dr

    from neural_brdf.inverse import fit as inverse

    fam = families.FAMILIES[data.draw(st.sampled_from(sorted(families.FAMILIES)))]
    free = {n: [data.draw(FREE) for _ in range(p.channels)] for n, p in fam.params.items()}
    typed = {n: mi.Float(z[0]) if len(z) == 1 else mi.Color3f(*z) for n, z in free.items()}
    values = fam.values(typed, dr)
    for n, p in fam.params.items():
        v = np.asarray(values[n], dtype=np.float64).reshape(-1)
        assert np.all(np.isfinite(v)) and np.all(v >= np.float32(p.bound.lo))
        assert np.all(v <= np.float32(p.bound.hi))
    keys = fam.to_mitsuba(values, dr)
    for k, v in keys.items():
        assert np.all(np.isfinite(np.asarray(v, dtype=np.float64))), k
    bsdf = inverse.mitsuba_bsdf(fam.element(fam.numbers({n: np.array(z) for n, z in free.items()})))
    rng = np.random.default_rng(0)
    wi, wo = (np.abs(rng.normal(size=(256, 3))) for _ in range(2))  # upper hemisphere
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    f = inverse.mitsuba_f_cos(bsdf, wi, wo)
    assert np.all(np.isfinite(f)) and np.all(f >= 0)


def test_a_parameter_below_float32s_range_reaches_mitsuba_as_zero(mi):
    """A fitted value Mitsuba's float32 parser cannot read (hypothesis found a
    principled's metallic of 1.6e-134, sin^2 of a tiny free variable) is written as 0,
    which float32 holds it as, in floats and in RGB; the BSDF loads and reads back 0."""
    from neural_brdf.inverse import fit as inverse

    el = inverse.bsdf_element(
        "principled", metallic=1.5530573483512763e-134, base_color=(1e-50, 0.5, -1e-45)
    )
    params = mi.traverse(inverse.mitsuba_bsdf(el))
    assert float(np.asarray(params["metallic.value"]).reshape(-1)[0]) == 0.0
    assert np.asarray(params["base_color.value"]).reshape(-1).tolist() == [0.0, 0.5, 0.0]
    assert inverse.xml_float(2e-38) == "2e-38" and inverse.xml_float(0.25) == "0.25"


# ------------------------------------------------------------------ the teacher
@pytest.mark.parametrize("name", ["diffuse", "roughplastic", "roughconductor_aniso", "blend"])
def test_teacher_xml_round_trips_through_mitsuba_target(mi, tmp_path, name):
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import starts
    from neural_brdf.measured.mitsuba import MitsubaTarget

    fam = families.FAMILIES[name]
    rng = np.random.default_rng(1)
    free = {n: rng.normal(size=p.channels) for n, p in fam.params.items()}
    if name == "roughconductor_aniso":
        free["alpha_u"], free["alpha_v"] = np.array([-1.5]), np.array([0.5])
    element = fam.element(fam.numbers(free))
    path = tmp_path / "teacher.xml"
    path.write_text(starts.teacher_xml(element))
    teacher = MitsubaTarget(path)
    assert teacher.excess is None  # albedo within 1: learned as it is
    assert teacher.anisotropic == (name == "roughconductor_aniso")
    z = rng.uniform(0.05, 1.0, 2000)
    phi = rng.uniform(0, 2 * math.pi, (2, 2000))
    dirs = [
        np.stack([np.sqrt(1 - z * z) * np.cos(p), np.sqrt(1 - z * z) * np.sin(p), z], -1)
        for p in phi
    ]
    wi, wo = dirs[0], np.roll(dirs[1], 7, axis=0)
    expected = inverse.mitsuba_f_cos(inverse.mitsuba_bsdf(element), wi, wo) / wo[:, 2:3]
    got = teacher.eval(wi, wo)
    assert np.allclose(got, expected, rtol=1e-5, atol=1e-7)
    assert np.abs(expected).max() > 0


def test_distill_trains_on_the_teacher_file(mi, tmp_path):
    import torch

    from neural_brdf import runfolder
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import starts
    from neural_brdf.train.model import RawBRDF

    cfg = config.from_dict(
        {
            "name": "images_test",
            "target": {"images": [{"scene": "view1.xml", "image": "view1.exr"}]},
            "model": {"hidden": [16], "activation": "relu"},
            "train": {"steps": 10, "progress": False, "warmup": 20},
            "data": {"batch_size": 1024, "pool_size": 32768},
        }
    )
    element = inverse.bsdf_element(
        "roughplastic", distribution="ggx", alpha=0.3, diffuse_reflectance=(0.5, 0.3, 0.2)
    )
    run = tmp_path / "init"
    state, info = starts.distill(cfg, element, run, 200)
    assert (run / starts.TEACHER_XML).read_text() == starts.teacher_xml(element)
    saved = config.load(run / runfolder.CONFIG)
    assert saved.target.mitsuba == str((run / starts.TEACHER_XML).absolute())
    assert "RoughPlastic" in info["target"]
    raw = RawBRDF.from_config(cfg.model)
    raw.load_state_dict(state)
    # the network learned the teacher: its error is well below an untrained one's
    assert info["raw_val_rel_rmse"] < 0.35, info
    wi = torch.tensor([[0.3, 0.1, 0.95], [0.5, -0.2, 0.84]])
    wo = torch.tensor([[-0.3, -0.1, 0.95], [0.0, 0.6, 0.8]])
    with torch.no_grad():
        f = raw(wi, wo).numpy()
    fc = inverse.mitsuba_f_cos(inverse.mitsuba_bsdf(element), wi.numpy(), wo.numpy())
    truth = fc / wo.numpy()[:, 2:3]
    assert np.all(np.abs(f - truth) < 0.5 * truth + 0.02), (f, truth)
    # a second start into the same folder replaces the first (a fresh run)
    starts.distill(cfg, element, run, 20)
    assert runfolder.is_run(run)


def test_an_overwritten_run_removes_the_teacher(mi, tmp_path):
    from neural_brdf import runfolder
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import starts

    cfg = config.from_dict(
        {
            "name": "images_test",
            "target": {"images": [{"scene": "view1.xml", "image": "view1.exr"}]},
            "model": {"hidden": [8]},
            "train": {"progress": False, "warmup": 0},
            "data": {"batch_size": 256, "pool_size": 4096},
        }
    )
    run = tmp_path / "run"
    folder = runfolder.Folder.open(run, resume=False, overwrite=False)
    folder.start(cfg.to_yaml())
    starts.distill(cfg, inverse.bsdf_element("diffuse"), folder.init, 5)
    runfolder.remove_run(run)
    assert not (folder.init / starts.TEACHER_XML).exists()


# ------------------------------------------------------------------ the choice's rule
def _candidate(name: str, terms):
    from neural_brdf.inverse import starts

    terms = np.asarray(terms, np.float64)
    fam = families.family(name)
    return starts.Candidate(
        family=name,
        params={},
        train_loss=float(terms.mean()),
        val_loss=float(terms.mean()),
        val_loss_plain=float(terms.mean()),
        seconds=0.0,
        steps=80,  # a Schedule() fit's
        complexity=fam.complexity,
        element=starts.STAND_IN,
        val_pixels=terms,
    )


def test_pick_takes_the_simpler_family_within_the_noise_and_never_a_much_worse_one():
    from neural_brdf.inverse import starts

    rng = np.random.default_rng(0)
    unit = np.repeat(np.arange(9), 16)  # 9 tiles of 16 pixels: a small film's split
    good = rng.gamma(2.0, 0.005, unit.size)
    # 2 % worse on average with tile-to-tile noise: a tie, the simpler family wins
    close = good * 1.02 + rng.normal(0.0, 0.002, unit.size)
    chosen, margins = starts.pick([_candidate("diffuse", close), _candidate("blend", good)], unit)
    assert chosen.family == "diffuse" and margins["diffuse"]["tied"]
    # 35 times worse but with one wild tile, so 2 standard errors would cover it: the
    # cap (TIE_MAX of the least) keeps the simple family out
    bad = good * 35.0
    bad[unit == 0] *= 200.0
    chosen, margins = starts.pick([_candidate("diffuse", bad), _candidate("blend", good)], unit)
    assert (
        margins["diffuse"]["above_best"] < starts.TIE_SIGMAS * margins["diffuse"]["standard_error"]
    )
    assert chosen.family == "blend" and not margins["diffuse"]["tied"]
    # without the cap the rule would have taken it
    chosen, _ = starts.pick(
        [_candidate("diffuse", bad), _candidate("blend", good)], unit, tie_max=math.inf
    )
    assert chosen.family == "diffuse"


def test_the_config_names_every_family_and_only_those():
    assert tuple(families.FAMILIES) == config.START_FAMILIES
    aniso = {n for n, f in families.FAMILIES.items() if f.anisotropic}
    assert set(config.ANISOTROPIC_FAMILIES) == aniso
    for name, fam in families.FAMILIES.items():  # a warm start's sources are fitted first
        order = list(families.FAMILIES)
        assert (fam.warm is None) == (not fam.warm_from), name
        assert all(order.index(n) < order.index(name) for n in fam.warm_from), name


def test_a_family_added_to_the_registry_alone_is_fitted_warm_started_and_chosen(
    mi, materials, monkeypatch
):
    """A new family is one entry of families.FAMILIES: the choice fits it, starts it from
    the family it names by its own rule (its steps counted behind it), scores it and
    may choose it, with nothing in starts.py naming it.  Here a diffuse started from the
    fitted diffuse with its reflectance a fifth too bright."""
    from neural_brdf.inverse import starts

    calls = []

    def brighter(fitted, views, mask_train):
        calls.append((sorted(fitted), len(views), len(mask_train)))
        return {"reflectance": np.asarray(fitted["diffuse"].params["reflectance"]) * 1.2}

    base = families.FAMILIES["diffuse"]
    toy = dataclasses.replace(base, name="diffuse_again", warm_from=("diffuse",), warm=brighter)
    monkeypatch.setitem(families.FAMILIES, "diffuse_again", toy)
    views = views_of(materials["diffuse"])
    sched = starts.Schedule(steps=6, spp=4, primal_spp=8, val_spp=16)
    # named before its source, it is still fitted after it (the registry's order)
    choice = starts.choose_start(views, ["diffuse_again", "diffuse"], seed=3, schedule=sched)
    assert [c.family for c in choice.candidates] == ["diffuse", "diffuse_again"]
    assert calls and calls[0][0] == ["diffuse"], calls
    by = {c.family: c for c in choice.candidates}
    assert by["diffuse_again"].before == by["diffuse"].total_steps >= 6
    assert all(math.isfinite(c.val_loss) for c in choice.candidates)
    assert choice.family in by and choice.summary()["candidates"][1]["family"] == "diffuse_again"
    # without the source fitted, the family starts from its own start
    assert starts.warm_start("diffuse_again", {}, views, []) is None


# ------------------------------------------------------------------ refining the choice
def test_refine_brings_an_off_start_closer_and_keeps_it(mi, materials):
    """From a diffuse start 15 % too bright, refine() (a tenth of the rate, iterates
    averaged) lands closer to the truth, and the validation split keeps it."""
    from neural_brdf.inverse import starts

    views = views_of(materials["diffuse"])
    train, held = starts.split_pixels(views, 0.3, seed=2)
    truth = np.array([0.6, 0.45, 0.3])
    kw = {"mask_train": train, "mask_val": held, "seed": 2}
    off = starts.fit_candidate(
        views,
        "diffuse",
        steps=0,
        init={"reflectance": truth * 1.15},
        schedule=starts.Schedule(val_spp=32),
        **kw,
    )
    images = config.Images(start_refine_steps=40, start_refine_spp=8, validation_spp=32)
    kept, info = starts.refine(views, off, schedule=starts.Schedule.refining(images), **kw)
    before = relative_error(off.params["reflectance"], truth)
    after = relative_error(kept.params["reflectance"], truth)
    assert before > 0.14 and after < before / 2, (before, after)
    assert info["kept"] and kept is not off
    assert info["val_loss_after"] < info["val_loss_before"] == off.val_loss
    assert info["params_before"] == off.params and info["params_after"] == kept.params


def test_refine_keeps_the_unrefined_start_when_the_split_prefers_it(mi, materials):
    from neural_brdf.inverse import starts

    views = views_of(materials["diffuse"])
    train, held = starts.split_pixels(views, 0.3, seed=2)
    kw = {"mask_train": train, "mask_val": held, "seed": 2}
    c = starts.fit_candidate(views, "diffuse", steps=0, init={"reflectance": [0.5, 0.5, 0.5]}, **kw)
    better = dataclasses.replace(c, val_loss=-1.0)  # no refinement can score below this
    sched = starts.Schedule(steps=4, spp=4, primal_spp=8, val_spp=16, lr=0.02, lr_end=0.1)
    kept, info = starts.refine(views, better, schedule=sched, **kw)
    assert kept is better and not info["kept"]
    assert info["val_loss_after"] > info["val_loss_before"]
    # no held-out pixels (a family named alone without a split): the refinement is kept
    none = [np.zeros_like(m) for m in held]
    c = starts.fit_candidate(
        views, "diffuse", steps=0, init={"reflectance": [0.5, 0.5, 0.5]}, mask_train=train,
        mask_val=none, seed=2,
    )  # fmt: skip
    assert math.isnan(c.val_loss)
    kept, info = starts.refine(views, c, schedule=sched, mask_train=train, mask_val=none, seed=2)
    assert kept is not c and info["kept"]


def test_averaged_fit_is_the_mean_of_the_iterates_from_its_step(mi, materials):
    """average_from = the last step gives the last iterate; from step 0 the mean of
    every iterate, which lags the last one on a fit that keeps moving one way."""
    from neural_brdf.inverse import starts

    views = views_of(materials["diffuse"])
    train, held = starts.split_pixels(views, 0.3, seed=2)
    kw = {"mask_train": train, "mask_val": held, "seed": 2, "steps": 6}
    kw["init"] = {"reflectance": [0.1, 0.1, 0.1]}  # far too dark: every step brightens
    last = starts.fit_candidate(views, "diffuse", **kw).params["reflectance"]
    same = starts.fit_candidate(views, "diffuse", average_from=5, **kw).params["reflectance"]
    mean = starts.fit_candidate(views, "diffuse", average_from=0, **kw).params["reflectance"]
    assert np.allclose(same, last, rtol=1e-6)
    assert np.all(np.asarray(mean) < np.asarray(last)) and np.all(np.asarray(mean) > 0.1)


def test_ctrl_c_inside_a_recorded_step_stops_the_fit(mi, materials, monkeypatch):
    """Ctrl-C (or SIGTERM, a KeyboardInterrupt too) that strikes while Dr.Jit records a
    step reaches the caller, which Dr.Jit hands a RuntimeError with the interrupt as its
    cause: it is not taken for a step Dr.Jit cannot record, after which the fit went on
    traced and the run ended as if never interrupted."""
    from neural_brdf.inverse import starts

    real = starts.render_loss_backward
    calls = []

    def interrupted_once(*args):
        calls.append(1)
        if len(calls) == 1:
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(starts, "render_loss_backward", interrupted_once)
    monkeypatch.setattr(starts, "UNFREEZABLE", set())
    views = views_of(materials["diffuse"])
    train, held = starts.split_pixels(views, 0.3, seed=2)
    with pytest.raises(KeyboardInterrupt):
        starts.fit_candidate(
            views, "diffuse", mask_train=train, mask_val=held, seed=2,
            schedule=starts.Schedule(steps=2, val_spp=8, freeze=True),
        )  # fmt: skip
    assert not starts.UNFREEZABLE  # nor marked as a step Dr.Jit cannot record
    # the cause chain: an interrupt anywhere in it, else none
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise RuntimeError("drjit.freeze(): error while recording") from e
    except RuntimeError as wrapped:
        assert isinstance(starts._interruption(wrapped), KeyboardInterrupt)
    assert starts._interruption(RuntimeError("cannot record", ValueError("x"))) is None


@pytest.mark.parametrize("name", config.START_FAMILIES)  # every family (the config's list)
def test_a_frozen_step_fits_what_a_traced_one_does(mi, materials, name, monkeypatch):
    """A family's fit with its step recorded once per view and replayed (Schedule.freeze,
    images.start_freeze) lands where the traced fit lands, to float rounding, and records
    once per view: a replay that read a stale array (one the frozen function does not
    take as an argument, such as a parameter set inside it) would differ by the steps'
    size, which the fit's own movement bounds below, or re-recorded at every step (no
    faster than tracing).  roughplastic is here because
    Mitsuba's plugin reads alpha on the host when its parameters change, which a
    recording refuses: the update runs outside the frozen function."""
    import drjit as dr

    from neural_brdf.inverse import starts

    made = []
    real = dr.freeze

    def spy(fn):
        made.append(real(fn))
        return made[-1]

    monkeypatch.setattr(dr, "freeze", spy)
    views = views_of(materials["roughplastic"])
    train, held = starts.split_pixels(views, 0.3, seed=2)
    fam = families.FAMILIES[name]
    kw = {"mask_train": train, "mask_val": held, "seed": 2}
    fits = {
        freeze: starts.fit_candidate(
            views, name, schedule=starts.Schedule(steps=6, val_spp=8, freeze=freeze), **kw
        )
        for freeze in (False, True)
    }
    start = starts.fit_candidate(
        views, name, schedule=starts.Schedule(steps=0, val_spp=8, freeze=False), **kw
    )

    def flat(c):
        return np.concatenate([np.ravel(np.asarray(c.params[n], np.float64)) for n in fam.params])

    traced, frozen, first = flat(fits[False]), flat(fits[True]), flat(start)
    moved = np.max(np.abs(traced - first) / np.abs(traced))
    assert moved > 1e-2, moved  # the fit moved: the comparison below can fail
    assert np.max(np.abs(frozen - traced) / np.abs(traced)) < 1e-4
    # a view records at its first step and again at its second (the first render adds
    # state to the scene: Dr.Jit counts more variables in it), then replays
    assert len(made) == 1 and made[0].n_recordings == 2 * len(views)


def test_a_scene_dr_jit_cannot_record_has_its_steps_traced(
    mi, materials, tmp_path, monkeypatch, capsys
):
    """Mitsuba refuses to record direct_projective in a frozen function: the fit says so
    on one stderr line (once per integrator), traces its steps, lands where a traced fit
    lands, and its candidate records that its steps were not frozen; a path scene's
    candidate records that they were."""
    from neural_brdf.inverse import starts

    monkeypatch.setattr(starts, "UNFREEZABLE", set())
    folder = tmp_path / "projective"
    shutil.copytree(materials["roughplastic"].parent, folder)
    for k in (1, 2, 3):
        xml = folder / f"view{k}.xml"
        tree = ET.parse(xml)
        integrator = tree.getroot().find("integrator")
        assert integrator is not None
        integrator.attrib["type"] = "direct_projective"
        for child in list(integrator):  # max_depth: not a property of this one
            integrator.remove(child)
        tree.write(xml)
    views = views_of(folder / "fit.yaml")
    train, held = starts.split_pixels(views, 0.3, seed=2)
    kw = {"mask_train": train, "mask_val": held, "seed": 2}
    fits = [
        starts.fit_candidate(
            views, "diffuse", schedule=starts.Schedule(steps=3, val_spp=8, freeze=freeze), **kw
        )
        for freeze in (True, False, True)
    ]
    err = capsys.readouterr().err
    assert err.count("images.start_freeze: Dr.Jit cannot record") == 1, err
    assert "'direct_projective'" in err and "\n" not in err.strip()
    assert starts.UNFREEZABLE == {"direct_projective"}
    assert not any(c.frozen for c in fits)
    # to float rounding: the failed step was retried traced, the later ones traced
    for c in (fits[0], fits[2]):
        assert np.allclose(c.params["reflectance"], fits[1].params["reflectance"], rtol=1e-5)
    assert fits[0].summary()["frozen_steps"] is False
    path_views = views_of(materials["roughplastic"])
    c = starts.fit_candidate(
        path_views, "diffuse", schedule=starts.Schedule(steps=2, val_spp=8), **kw
    )
    assert c.frozen and c.summary()["frozen_steps"] is True


def test_the_choice_rule_comes_from_the_config(mi, materials, monkeypatch):
    """network_start hands images.start_tie_tol, start_tie_sigmas and start_tie_max to
    choose_start, whose record names them; starts.pick's defaults are the config's."""
    from neural_brdf.inverse import starts

    assert (starts.TIE_TOL, starts.TIE_SIGMAS, starts.TIE_MAX) == (
        config.Images().start_tie_tol,
        config.Images().start_tie_sigmas,
        config.Images().start_tie_max,
    )
    seen = {}

    def choose(views, names, **kw):
        seen.update(kw)
        raise RuntimeError("stop here")

    from neural_brdf.inverse import fit as inverse

    monkeypatch.setattr(starts, "choose_start", choose)
    path = materials["diffuse"]
    ties = ["images.start_tie_tol=0.07", "images.start_tie_sigmas=3.5", "images.start_tie_max=0.4"]
    cfg = config.load(path, ["images.start=auto", *ties, "images.start_catch_up=false"])
    views = views_of(path)
    inverse.split_views(views, cfg.images, cfg.train.seed)
    for v in views:
        v.object = starts.object_mask(v)
    with pytest.raises(RuntimeError, match="stop here"):
        starts.network_start(cfg, views, path.parent / "init")
    assert (seen["tie_tol"], seen["sigmas"], seen["tie_max"]) == (0.07, 3.5, 0.4)
    assert seen["catch_up_sources"] is False and config.Images().start_catch_up is True


def test_the_start_schedules_come_from_the_config():
    """Every setting of the starts' fits is a key of the images section."""
    from neural_brdf.inverse import starts

    images = config.Images(
        start_steps=7,
        start_lr=0.3,
        start_lr_end=0.2,
        start_spp=5,
        start_primal_spp=9,
        validation_spp=11,
        start_refine_steps=13,
        start_refine_lr=0.04,
        start_refine_lr_end=0.5,
        start_refine_spp=6,
        start_freeze=False,
    )
    assert starts.Schedule.of(images) == starts.Schedule(
        steps=7, spp=5, primal_spp=9, val_spp=11, lr=0.3, lr_end=0.2, freeze=False
    )
    assert starts.Schedule.refining(images) == starts.Schedule(
        steps=13, spp=6, primal_spp=12, val_spp=11, lr=0.04, lr_end=0.5, freeze=False
    )
    assert starts.Schedule.of(config.Images()).freeze and starts.Schedule().freeze
    assert starts.Schedule.of(config.Images()).steps == starts.Schedule().steps  # null: 80


# ------------------------------------------------------------------ the model after the start
def _images_cfg(model, images=None):
    d = {"target": {"images": [{"scene": "v.xml", "image": "v.exr"}]}, "model": model}
    return config.from_dict(d | ({"images": images} if images else {}))


@pytest.mark.parametrize(
    "family, images, coords, encoding",
    [
        ("roughconductor_aniso", {}, "half_disc", "anisotropic"),
        ("roughconductor", {}, "theta", "isotropic"),
        ("blend", {}, "theta", "isotropic"),
        ("diffuse", {"isotropic_encoding": "model"}, "theta", "anisotropic"),
        ("roughconductor_aniso", {"anisotropic_grid": "model"}, "theta", "anisotropic"),
    ],
)
def test_the_start_sets_the_network_grid_and_encoding(family, images, coords, encoding):
    """model_for_start: after an anisotropic family (and images.anisotropic_grid:
    half_disc) the network's grid is over the half vector's disc; after any other family
    (and images.isotropic_encoding: isotropic) the network's encoding is isotropic;
    with either set to model, model's keys are kept; nothing else changes."""
    from neural_brdf.inverse import starts

    cfg = _images_cfg({"encoding": "anisotropic", "grid": {"size": 16, "coords": "theta"}}, images)
    out = starts.model_for_start(cfg, family)
    assert (out.model.grid.coords, out.model.encoding) == (coords, encoding)
    a, b = cfg.model_dump(), out.model_dump()
    b["model"]["grid"]["coords"] = a["model"]["grid"]["coords"]
    b["model"]["encoding"] = a["model"]["encoding"]
    assert a == b


@pytest.mark.parametrize(
    "model, family",
    [
        ({"encoding": "isotropic", "grid": {"size": 16}}, "roughconductor_aniso"),  # no disc
        ({"encoding": "anisotropic", "grid": {"size": 0}}, "roughconductor_aniso"),  # no grid
        (
            {"encoding": "anisotropic", "grid": {"size": 16, "coords": "half_disc"}},
            "roughconductor_aniso",
        ),
        ({"encoding": "isotropic", "grid": {"size": 16}}, "diffuse"),  # isotropic already
        # the isotropic encoding has no grid over the half vector's disc
        ({"encoding": "anisotropic", "grid": {"size": 16, "coords": "half_disc"}}, "diffuse"),
        ({"encoding": "raw"}, "diffuse"),  # not reciprocal: an ablation, left as it is
    ],
)
def test_the_model_is_left_alone_where_it_cannot_or_need_not_change(model, family):
    from neural_brdf.inverse import starts

    cfg = _images_cfg(model)
    assert starts.model_for_start(cfg, family) is cfg


def test_a_network_of_the_isotropic_encoding_after_an_isotropic_start_cannot_vary_in_phi_h():
    """The point of images.isotropic_encoding: the network built from the config
    model_for_start returns gives the same value for a pair rotated about the normal
    (the half vector's azimuth), whatever its weights; the anisotropic one does not."""
    import torch

    from neural_brdf.inverse import starts
    from neural_brdf.train.model import RawBRDF

    cfg = _images_cfg({"encoding": "anisotropic", "grid": {"size": 8, "coords": "theta"}})
    torch.manual_seed(0)
    wi = torch.nn.functional.normalize(torch.rand(64, 3) + torch.tensor([0.0, 0.0, 0.3]), dim=-1)
    wo = torch.nn.functional.normalize(torch.rand(64, 3) + torch.tensor([0.0, 0.0, 0.3]), dim=-1)
    c, s = math.cos(1.1), math.sin(1.1)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    spread = {}
    for family in ("diffuse", "roughconductor_aniso"):
        net = RawBRDF.from_config(starts.model_for_start(cfg, family).model)
        with torch.no_grad():
            for p in net.parameters():  # any weights, not a trained (possibly flat) net
                p.normal_(0.0, 0.5)
            a, b = net(wi, wo), net(wi @ rot.T, wo @ rot.T)
        spread[family] = float((a - b).abs().max() / a.abs().max())
    assert spread["diffuse"] < 1e-5
    assert spread["roughconductor_aniso"] > 1e-3


@pytest.mark.parametrize(
    "losses, rounds, gain, ran, kept_round",
    [
        ([0.5, 0.3, 0.2, 0.19, 0.1], 5, 0.1, 4, 4),  # gains 50, 40, 33, 5 %: the 4th the last
        ([0.5, 0.3, 0.2, 0.1], 2, 0.1, 2, 2),  # the cap
        ([0.5, 0.3, 0.35], 4, 0.1, 3, 2),  # the third rose: not kept, and the end
        ([1.2], 4, 0.1, 1, 0),  # the first rose: the choice itself is kept
        ([0.5, 0.3], 1, 0.1, 1, 1),  # one round: refine() alone
    ],
)
def test_refine_rounds_continue_while_the_split_gains(
    monkeypatch, losses, rounds, gain, ran, kept_round
):
    """Each round starts from the last one kept; another runs only while the last was kept
    and cut the held-out loss by more than ``gain``; the summary holds the first's
    'before' and the kept result's 'after'."""
    from neural_brdf.inverse import starts

    seen: list[dict] = []

    def fake_fit(views, family, *, init, **kw):
        seen.append(dict(init))
        k = len(seen)
        return dataclasses.replace(
            chosen, params={"round": k}, val_loss=losses[k - 1], seconds=1.0, steps=60
        )

    chosen = starts.Candidate(
        family="diffuse",
        params={"round": 0},
        train_loss=1.0,
        val_loss=1.0,
        val_loss_plain=1.0,
        seconds=0.0,
        steps=80,
        complexity=3,
        element=ET.Element("bsdf"),
    )
    monkeypatch.setattr(starts, "fit_candidate", fake_fit)
    sched = starts.Schedule(steps=60, spp=16, primal_spp=32, val_spp=64, lr=0.02, lr_end=0.1)
    kept, summary = starts.refine_rounds(
        [], chosen, rounds=rounds, gain=gain, mask_train=[], mask_val=[], seed=0, schedule=sched
    )
    assert len(seen) == ran and summary["rounds"] == losses[:ran]
    # each round started from the parameters of the round kept before it
    assert [s["round"] for s in seen] == [min(k, kept_round) for k in range(ran)]
    assert kept.params == {"round": kept_round}
    assert summary["kept"] == (kept_round > 0) and summary["val_loss_before"] == 1.0
    assert summary["val_loss_after"] == (losses[kept_round - 1] if kept_round else losses[0])
    assert summary["steps"] == 60 and summary["seconds"] == ran


# ------------------------------------------------------------------ the contenders
def _continued_to(table: dict[str, np.ndarray], calls: list[str]):
    """A stand-in for fit_candidate continuing a family from ``init``: the candidate of
    each family in ``table`` fitted to those held-out pixel terms (else its first
    fit's, passed as ``init["terms"]``), 2 s each, every call recorded."""

    def fake(views, family, *, init=None, **kw):
        calls.append(family)
        terms = table.get(family, (init or {}).get("terms"))
        c = _candidate(family, terms)
        return dataclasses.replace(c, params={"continued": True}, seconds=2.0)

    return fake


def _first(name: str, terms):
    c = _candidate(name, terms)
    return dataclasses.replace(c, params={"terms": terms})


def test_continuing_the_contenders_lets_a_family_that_stopped_short_win(monkeypatch):
    """images.start_continue_within: every family within that factor of the least
    held-out loss fits further and the choice is made again on the continued losses, so
    a family whose first fit stopped short (the blue principled's own family at 1.3 x
    the roughplastic under point lights) wins; a family beyond the factor is not
    continued, a continued fit that scores worse is not kept, null continues none, and
    neither does a chosen start within the rule's cap of the targets' noise."""
    from neural_brdf.inverse import starts

    rng = np.random.default_rng(1)
    unit = np.repeat(np.arange(12), 16)
    base = rng.gamma(2.0, 0.0005, unit.size)
    cands = [
        _first("diffuse", base * 6.0),  # beyond the factor: never continued
        _first("roughplastic", base),  # the least: chosen first
        _first("principled", base * 1.3),  # a contender
    ]
    kw = dict(mask_train=[], mask_val=[], seed=0, schedule=starts.Schedule(), unit=unit)
    calls: list[str] = []
    continued = {"roughplastic": base * 1.01, "principled": base * 0.002}
    monkeypatch.setattr(starts, "fit_candidate", _continued_to(continued, calls))
    first, _ = starts.pick(cands, unit)
    assert first.family == "roughplastic"
    chosen, pool, done, margins = starts.contend([], cands, first, within=2.0, **kw)
    assert calls == ["roughplastic", "principled"] and list(done) == calls
    assert chosen.family == "principled" and chosen.params == {"continued": True}
    assert not margins["roughplastic"]["tied"] and margins["principled"]["above_best"] == 0.0
    # the roughplastic's continued fit scored worse: its first one stands, the steps it
    # was given counted behind it
    assert not done["roughplastic"]["kept"] and pool[1].params is cands[1].params
    assert pool[1].val_loss == cands[1].val_loss and pool[1].total_steps == 2 * 80
    assert done["principled"]["kept"] and pool[0] is cands[0]
    # the factor bounds the contenders: at 1.2 the roughplastic alone, which stays
    calls.clear()
    chosen, _, done, _ = starts.contend([], cands, first, within=1.2, **kw)
    assert calls == ["roughplastic"] and chosen.family == "roughplastic"
    # null: none, the choice as it was
    calls.clear()
    chosen, pool, done, margins = starts.contend([], cands, first, within=None, **kw)
    assert calls == [] and chosen is first and done == {} and pool == cands
    # the chosen start within TIE_MAX of the targets' noise is at its floor: none
    least = cands[1].val_loss
    calls.clear()
    chosen, _, _, _ = starts.contend([], cands, first, within=2.0, noise=least / 1.2, **kw)
    assert calls == [] and chosen is first
    chosen, _, _, _ = starts.contend([], cands, first, within=2.0, noise=least / 1.3, **kw)
    assert calls == ["roughplastic", "principled"] and chosen.family == "principled"
    # a poor start (its loss far above the noise) is not exempt: the development set's
    # clay, poor under both captures, gained under the sky (docs/inverse.md)
    calls.clear()
    chosen, _, _, _ = starts.contend([], cands, first, within=2.0, noise=least / 1000, **kw)
    assert calls == ["roughplastic", "principled"]


def test_the_contenders_are_capped_at_the_least_losses_with_the_chosen_one(monkeypatch):
    """images.start_continue_max: of the families within the factor, the chosen one and
    the others of least held-out loss, that many in all, in the order fitted (the test
    set's retroreflector, a poor start, had all six within it under the studio)."""
    from neural_brdf.inverse import starts

    rng = np.random.default_rng(2)
    unit = np.repeat(np.arange(12), 16)
    base = rng.gamma(2.0, 0.0005, unit.size)
    # every family within a factor of 2 of the least; the simplest, not the least, chosen
    scale = {
        "diffuse": 1.01,
        "roughplastic": 1.3,
        "principled": 1.1,
        "roughconductor": 1.5,
        "roughconductor_aniso": 1.2,
        "blend": 1.0,
    }
    cands = [_first(name, base * k) for name, k in scale.items()]
    chosen = cands[0]
    assert starts.contenders(cands, chosen, 2.0) == cands  # no cap: all six
    three = starts.contenders(cands, chosen, 2.0, most=3)
    assert [c.family for c in three] == ["diffuse", "principled", "blend"]
    two = starts.contenders(cands, chosen, 2.0, most=2)
    assert [c.family for c in two] == ["diffuse", "blend"]
    # the chosen one is always among them, even where its loss is not among the least
    worst = cands[3]
    assert [c.family for c in starts.contenders(cands, worst, 2.0, most=2)] == [
        "roughconductor",
        "blend",
    ]
    # a cap above the number within the factor changes nothing; the factor still bounds
    assert starts.contenders(cands, chosen, 2.0, most=10) == cands
    assert [c.family for c in starts.contenders(cands, chosen, 1.15, most=3)] == [
        "diffuse",
        "principled",
        "blend",
    ]
    # contend() fits those alone
    calls: list[str] = []
    monkeypatch.setattr(starts, "fit_candidate", _continued_to({}, calls))
    kw = dict(mask_train=[], mask_val=[], seed=0, schedule=starts.Schedule(), unit=unit)
    starts.contend([], cands, chosen, within=2.0, most=3, **kw)
    assert calls == ["diffuse", "principled", "blend"]


def test_the_cap_on_the_contenders_is_a_config_key():
    """images.start_continue_max is validated like every key: null lifts the cap, and
    below 2 (no contender but the chosen one) is refused with a line naming it."""
    from neural_brdf.errors import ConfigError

    assert config.load(None, ["images.start_continue_max=null"]).images.start_continue_max is None
    assert config.load(None, ["images.start_continue_max=4"]).images.start_continue_max == 4
    with pytest.raises(ConfigError, match="images.start_continue_max"):
        config.load(None, ["images.start_continue_max=1"])


def test_a_continued_fit_that_diverged_is_never_kept(monkeypatch):
    """A contender (or a refinement) whose continued fit ends NaN or infinite keeps its
    first fit: NaN compares False with anything, and the rule was ``after > before``."""
    from neural_brdf.inverse import starts

    assert starts.no_worse(1.0, 2.0) and starts.no_worse(2.0, 2.0)
    assert not starts.no_worse(3.0, 2.0)
    assert not starts.no_worse(math.nan, 2.0) and not starts.no_worse(math.inf, 2.0)
    assert starts.no_worse(math.nan, math.nan)  # no held-out pixels: nothing prefers either
    assert starts.no_worse(1.0, math.inf) and not starts.no_worse(math.inf, math.inf)
    rng = np.random.default_rng(2)
    unit = np.repeat(np.arange(12), 16)
    base = rng.gamma(2.0, 0.0005, unit.size)
    cands = [_first("roughplastic", base), _first("principled", base * 1.3)]
    calls: list[str] = []
    diverged = {"roughplastic": base * 0.9, "principled": np.full(unit.size, np.nan)}
    monkeypatch.setattr(starts, "fit_candidate", _continued_to(diverged, calls))
    first, _ = starts.pick(cands, unit)
    kw = dict(mask_train=[], mask_val=[], seed=0, schedule=starts.Schedule())
    chosen, pool, done, _ = starts.contend([], cands, first, within=2.0, unit=unit, **kw)
    assert calls == ["roughplastic", "principled"]
    assert not done["principled"]["kept"] and pool[1].params is cands[1].params
    assert done["roughplastic"]["kept"] and chosen.family == "roughplastic"
    assert math.isfinite(chosen.val_loss)
    kept, summary = starts.refine([], cands[1], **kw)  # the principled diverges again
    assert kept is cands[1] and not summary["kept"]
    kept, summary = starts.refine([], cands[0], **kw)  # the roughplastic gains
    assert kept is not cands[0] and summary["kept"] and kept.val_loss < cands[0].val_loss


def _network_start_fakes(monkeypatch, cands, continued, noise):
    """network_start's stages replaced: the choice picks among ``cands``, a contender's
    further fit scores ``continued[family]`` (its own losses otherwise), a refinement
    keeps its start (3 s), the distillation returns at once, and the targets' noise is
    ``noise["value"]``.  Returns (the families fitted further, the candidates refined)."""
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import starts

    def choose(views, names, **kw):
        chosen, margins = starts.pick(cands)
        return starts.Choice(
            family=chosen.family,
            element=chosen.element,
            params=chosen.params,
            candidates=cands,
            margins=margins,
            val_share=0.2,
            block=4,
            tie_tol=0.02,
            sigmas=2.0,
            tie_max=0.25,
            seconds=1.0,
        )

    refined: list[object] = []

    def refine_rounds(views, c, **kw):
        refined.append(c)
        return c, {
            "val_loss_before": c.val_loss,
            "val_loss_after": c.val_loss,
            "kept": False,
            "params_before": c.params,
            "params_after": c.params,
            "rounds": [c.val_loss],
            "seconds": 3.0,
        }

    def distill(cfg, element, folder, steps, *, poor=False):
        return {}, {"seconds": 0.5, "steps": steps, "poor": poor}  # what it was asked for

    calls: list[str] = []
    monkeypatch.setattr(starts, "choose_start", choose)
    monkeypatch.setattr(starts, "fit_candidate", _continued_to(continued, calls))
    monkeypatch.setattr(starts, "refine_rounds", refine_rounds)
    monkeypatch.setattr(starts, "distill", distill)
    # the starts read the targets' noise through the views' layer, the fit through its own name
    monkeypatch.setattr(starts.inverse, "target_noise", lambda views: noise["value"])
    monkeypatch.setattr(inverse, "target_noise", lambda views: noise["value"])
    return calls, refined


def _split_views(path, cfg):
    """The example's views of ``path`` with ``cfg``'s split and their object masks."""
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import starts

    views = views_of(path)
    inverse.split_views(views, cfg.images, cfg.train.seed)
    for v in views:
        v.object = starts.object_mask(v)
    return views


def test_network_start_records_the_contenders_and_the_choice_made_again(mi, materials, monkeypatch):
    """metrics.json's start (training.init.start): each contender's continued held-out
    loss beside its first figures, the first choice where the new one differs, the new
    choice's refinement under ``refine`` (from its continued fit), and every fit's time
    in the start's; at the targets' noise, no contender."""
    from neural_brdf.inverse import starts

    rng = np.random.default_rng(3)
    path = materials["diffuse"]
    cfg = config.load(path, ["images.start=auto", "images.start_continue_within=2"])
    views = _split_views(path, cfg)
    n = int(sum(m.sum() for m in starts.run_masks(views)[1]))
    base = rng.gamma(2.0, 0.001, n)
    cands = [
        _first("diffuse", base * 5.0),
        _first("roughplastic", base),
        _first("principled", base * 1.5),
    ]
    noise = {"value": float(base.mean()) / 100.0}  # far below the chosen start's loss
    calls, refined = _network_start_fakes(monkeypatch, cands, {"principled": base * 0.01}, noise)
    _, info, _ = starts.network_start(cfg, views, path.parent / "init")
    s = info["start"]
    assert calls == ["roughplastic", "principled"]
    assert s["family"] == "principled" and s["first_choice"] == "roughplastic"
    assert s["continue_within"] == 2.0 and s["uncontested"] is None
    assert [c.family for c in refined] == ["principled"] and refined[0].params == {
        "continued": True
    }
    assert s["refine"]["val_loss_before"] == s["val_loss"] == refined[0].val_loss
    by = {c["family"]: c for c in s["candidates"]}
    assert "continued_val_loss" not in by["diffuse"]
    assert by["principled"]["continued_val_loss"] < by["principled"]["val_loss"]
    assert by["roughplastic"]["continued_val_loss"] == by["roughplastic"]["val_loss"]
    assert s["seconds"] == pytest.approx(1.0 + 2 * 2.0 + 3.0)
    assert info["seconds"] == pytest.approx(0.5 + s["seconds"])
    # at the targets' noise the chosen start is at its floor: no contender continued
    calls.clear()
    refined.clear()
    noise["value"] = float(base.mean())
    _, info, _ = starts.network_start(cfg, views, path.parent / "init2")
    s = info["start"]
    assert calls == [] and [c.family for c in refined] == ["roughplastic"]
    assert s["family"] == "roughplastic" and s["uncontested"] == "at its floor"
    assert "first_choice" not in s
    assert not any("continued_val_loss" in c for c in s["candidates"])


def test_a_first_choice_far_above_the_noise_is_poor_at_once(mi, materials, monkeypatch, capsys):
    """images.poor_start_early_loss: a first choice whose held-out loss exceeds the
    targets' noise by more than the limit fits no contender further and is not refined
    (the development set's amber retroreflector: 0.21 above its noise, where the most the
    contenders and the refinement took off a first choice was 0.003); metrics.json says
    why, stderr says so, the start's time holds neither, and the fit then calls the start
    poor.  Just below the limit both run as before; null never skips them."""
    from neural_brdf.inverse import fit as inverse
    from neural_brdf.inverse import starts

    rng = np.random.default_rng(4)
    path = materials["diffuse"]
    views = _split_views(path, config.load(path, ["images.start=auto"]))
    n = int(sum(m.sum() for m in starts.run_masks(views)[1]))
    base = rng.gamma(2.0, 0.01, n)  # a mean loss about 0.02
    cands = [_first("diffuse", base), _first("blend", base * 1.2)]
    least = float(base.mean())
    noise = {"value": 0.001}
    calls, refined = _network_start_fakes(monkeypatch, cands, {}, noise)

    def run(limit, folder, poor_off=False):
        sets = ["images.start=auto", f"images.poor_start_early_loss={limit}"]
        cfg = config.load(path, [*sets, *(["images.poor_start_loss=null"] if poor_off else [])])
        calls.clear()
        refined.clear()
        return starts.network_start(cfg, views, path.parent / folder, report=print)[1]

    info = run(least - 0.001 - 1e-4, "init_far")  # the excess just above the limit
    s = info["start"]
    assert calls == [] and refined == []
    assert s["uncontested"] == "far above its floor" and "refine" not in s
    assert s["family"] == "diffuse" and s["val_loss"] == cands[0].val_loss
    assert s["seconds"] == pytest.approx(1.0)  # the choice alone
    out = capsys.readouterr().out
    assert "images.poor_start_early_loss" in out and "poor at once" in out
    # the fit's rule then calls it poor (the limit is at least images.poor_start_loss),
    # and it was distilled as one: images.poor_start_train_steps (and its rate)
    assert inverse.poor_start(info, 0.0015, noise["value"], 450)
    assert info["poor"] and info["steps"] == config.Images().poor_start_train_steps
    # just below the limit, with null, and with no start poor: the contenders and the
    # refinement as before
    for limit, more in ((least - 0.001 + 1e-4, []), ("null", []), (0.0015, [None])):
        got = run(limit, f"init_{limit}_{len(more)}", poor_off=bool(more))
        s = got["start"]
        assert calls == ["diffuse", "blend"] and [c.family for c in refined] == ["diffuse"]
        # poor but for the null limit: distilled as a poor start or a good one
        assert got["poor"] is (not more)
        images = config.Images()
        assert got["steps"] == (images.start_train_steps if more else images.poor_start_train_steps)
        assert s["uncontested"] is None and "refine" in s
    # a start at its floor is not poor at once, however far above a noise that high it is
    noise["value"] = least / 1.2
    s = run(0.0015, "init_floor")["start"]
    assert least - noise["value"] > 0.0015  # above the limit, but within TIE_MAX of the noise
    assert s["uncontested"] == "at its floor" and calls == []
    assert [c.family for c in refined] == ["diffuse"] and "refine" in s


def test_poor_at_once_is_a_config_key_no_lower_than_the_poor_limit():
    """images.poor_start_early_loss is validated like every key: a start poor at once
    must be poor, so it is refused below images.poor_start_loss by a line naming it;
    null, here or in images.poor_start_loss (no start poor), never skips."""
    from neural_brdf.errors import ConfigError

    assert config.load(None, []).images.poor_start_early_loss == 0.03
    off = config.load(None, ["images.poor_start_early_loss=null"])
    assert off.images.poor_start_early_loss is None
    same = config.load(None, ["images.poor_start_early_loss=0.0015"])
    assert same.images.poor_start_early_loss == same.images.poor_start_loss
    assert same.images.early_poor_loss == 0.0015
    assert config.load(None, ["images.poor_start_loss=null"]).images.early_poor_loss is None
    for bad in (["images.poor_start_early_loss=0.001"], ["images.poor_start_early_loss=0"]):
        with pytest.raises(ConfigError, match="images.poor_start_early_loss"):
            config.load(None, bad)


# ------------------------------------------------------------------ an inconclusive split
def _tile_ids(mask: np.ndarray, block: int = 4) -> set[int]:
    from neural_brdf.inverse import starts

    return set(np.unique(starts.tiles(mask.shape, block)[mask]).tolist())


def _per_pixel(
    terms: dict[str, list[np.ndarray]],
    calls: list[tuple[str, bool]],
    continued: dict[str, list[np.ndarray]] | None = None,
):
    """A stand-in for fit_candidate whose candidate scores, on whatever pixels it is
    held out on, the per-pixel terms ``terms[family]`` (one (H, W) map per view), or
    ``continued[family]`` when it is given a start (a fit continued from its own), 2 s
    each; every call recorded with whether it was given a start (a warm start)."""

    def fake(views, family, *, mask_train, mask_val, init=None, **kw):
        calls.append((family, init is not None))
        for tr, va in zip(mask_train, mask_val, strict=True):
            assert not (tr & va).any()  # a fold's fit never sees its held-out pixels
        table = continued if init is not None and family in (continued or {}) else terms
        px = np.concatenate([t[m] for t, m in zip(table[family], mask_val, strict=True)])
        c = _candidate(family, px)
        return dataclasses.replace(c, params={"fold": True}, seconds=2.0)

    return fake


def _a_lobe_on_few_tiles(train, held, seed=5, lobe_tiles=8, gain=0.004, block=4):
    """Per-pixel held-out terms of ``principled`` and ``clearcoat`` on views of the
    masks ``train``/``held``: the same noisy floor, and principled worse by ``gain`` on
    ``lobe_tiles`` tiles of the object, one of them in the split and the others in the
    training tiles (a clear coat's highlights, as on the development torus)."""
    from neural_brdf.inverse import starts

    rng = np.random.default_rng(seed)
    floor = [rng.gamma(4.0, 0.00025, m.shape) for m in train]
    t = starts.tiles(train[0].shape, block)
    on_held = sorted(_tile_ids(held[0], block))[:1]
    on_train = sorted(_tile_ids(train[0], block) - _tile_ids(held[0], block))
    picked = on_held + list(rng.choice(on_train, lobe_tiles - 1, replace=False))
    lobe = [np.isin(t, picked)] + [np.zeros_like(m) for m in train[1:]]
    coat = [f + rng.normal(0.0, 0.0001, f.shape) for f in floor]
    bare = [c + gain * m for c, m in zip(coat, lobe, strict=True)]
    return {"principled": bare, "clearcoat": coat}, picked


def _masks(shape=(48, 48), share=0.2, seed=0, block=4):
    """(train, held): one view's object (a disc) and a tile split of it."""
    from neural_brdf.inverse import starts

    h, w = shape
    y, x = np.mgrid[:h, :w]
    obj = (x - w / 2 + 0.5) ** 2 + (y - h / 2 + 0.5) ** 2 < (0.45 * h) ** 2
    t = starts.tiles(shape, block)
    ids = np.unique(t[obj])
    rng = np.random.default_rng(seed)
    held = obj & np.isin(t, rng.choice(ids, round(share * ids.size), replace=False))
    return [obj & ~held], [held]


def test_the_folds_cut_the_training_tiles_and_follow_the_seed():
    from neural_brdf.inverse import starts

    train, held = _masks()
    folds = starts.fold_masks(train, 4, seed=3, folds=3)
    assert len(folds) == 3
    union = np.zeros_like(train[0])
    sizes = []
    for f in folds:
        assert not (f[0] & union).any() and not (f[0] & held[0]).any()
        assert not (_tile_ids(f[0]) & set().union(*(_tile_ids(g[0]) for g in folds if g is not f)))
        union |= f[0]
        sizes.append(len(_tile_ids(f[0])))
    assert (union == train[0]).all() and max(sizes) - min(sizes) <= 1
    again = starts.fold_masks(train, 4, seed=3, folds=3)
    assert all((a[0] == b[0]).all() for a, b in zip(folds, again, strict=True))
    other = starts.fold_masks(train, 4, seed=4, folds=3)
    assert any((a[0] != b[0]).any() for a, b in zip(folds, other, strict=True))


def test_an_inconclusive_split_is_settled_over_folds_of_the_training_tiles(monkeypatch):
    """A lobe seen on eight tiles, one of them in the split: the split ties the family
    that has it with the simpler one by its standard error alone (inconclusive), and the
    two fitted again on folds of the training tiles, each held out in turn, choose it
    over every tile; the warm-started family after the one it starts from in each fold.
    Without the lobe (the same noise), the folds keep the simpler family; a tie within
    start_tie_tol, or a best family no more complex, is not inconclusive."""
    from neural_brdf.inverse import starts

    train, held = _masks()
    terms, _ = _a_lobe_on_few_tiles(train, held)
    calls: list[tuple[str, bool]] = []
    monkeypatch.setattr(starts, "fit_candidate", _per_pixel(terms, calls))
    kw = dict(mask_train=train, mask_val=held, seed=0)
    first = {n: starts.fit_candidate([None], n, **kw) for n in ("principled", "clearcoat")}
    # as choose_start fits the coat: from the principled, whose steps are behind it
    first["clearcoat"] = dataclasses.replace(first["clearcoat"], before=80)
    chosen, margins = starts.pick(list(first.values()), starts.units(held, 4))
    assert chosen.family == "principled" and margins["principled"]["tied"]
    rival = starts.inconclusive(list(first.values()), chosen)
    assert rival is first["clearcoat"]
    calls.clear()
    check = dict(folds=2, block=4, schedule=starts.Schedule(), **kw)
    won, s = starts.cross_check([None], first["principled"], rival, **check)
    assert won == "clearcoat" and s["chosen"] == "clearcoat"
    # the split's principled scored after as many steps again as the coat had from it,
    # and in each fold: the principled, the coat from it, the principled continued
    assert (
        calls
        == [("principled", True)]
        + [
            ("principled", False),
            ("clearcoat", True),
            ("principled", True),
        ]
        * 2
    )
    assert s["continued"] == ["principled"]
    assert s["tiles"] == len(_tile_ids(train[0] | held[0])) and s["folds_fitted"] == 2
    assert s["rival_gain"] > starts.TIE_SIGMAS * s["standard_error"]
    assert not s["margins"]["principled"]["tied"]
    # the split alone would not have: the folds are what decide
    assert (
        margins["principled"]["above_best"]
        < starts.TIE_SIGMAS * margins["principled"]["standard_error"]
    )
    # the coat's gain is the principled's shorter fit: continued as many steps as the
    # coat had from it, the principled scores as well, and stays (the isotropic
    # development silver against its anisotropic conductor)
    caught_up = {"principled": terms["clearcoat"]}
    monkeypatch.setattr(starts, "fit_candidate", _per_pixel(terms, calls, caught_up))
    won, s = starts.cross_check([None], first["principled"], rival, **check)
    assert won == "principled" and s["margins"]["principled"]["tied"]
    # no lobe: both score the same floor up to noise, and the simpler family stays
    flat = {
        "principled": terms["clearcoat"],
        "clearcoat": [
            t + np.random.default_rng(9).normal(0.0, 0.0001, t.shape) for t in terms["clearcoat"]
        ],
    }
    monkeypatch.setattr(starts, "fit_candidate", _per_pixel(flat, calls))
    won, s = starts.cross_check([None], first["principled"], rival, **check)
    assert won == "principled" and s["margins"]["principled"]["tied"]
    # not inconclusive: the best no more complex than the chosen one, or within tie_tol
    assert starts.inconclusive([first["clearcoat"]], first["clearcoat"]) is None
    p, c = first["principled"], first["clearcoat"]
    assert starts.inconclusive([p, c], p, tie_tol=(p.val_loss - c.val_loss) / c.val_loss) is None
    assert starts.inconclusive([p, c], p, tie_tol=0.5 * (p.val_loss - c.val_loss) / c.val_loss)


def test_network_start_settles_an_inconclusive_choice_and_says_so(mi, materials, monkeypatch):
    """metrics.json's start: a choice the split tied by its standard error alone is
    cross-checked (images.start_cross_folds folds), the family the folds prefer is
    refined and distilled, the first choice and the check are recorded, and the check's
    fits count in the start's time; with images.start_cross_folds 0 the split's choice
    stands and no check is made."""
    from neural_brdf.inverse import starts

    path = materials["diffuse"]
    cfg = config.load(path, ["images.start=auto"])
    views = _split_views(path, cfg)
    train, held = starts.run_masks(views)
    # the lobe on the first view's tiles (a quarter of them: a 24 x 24 film has 36)
    terms, _ = _a_lobe_on_few_tiles(train, held, lobe_tiles=9, gain=0.0005)
    first = {}
    for n in ("principled", "clearcoat"):
        px = np.concatenate([t[m] for t, m in zip(terms[n], held, strict=True)])
        first[n] = _first(n, px)
    first["clearcoat"] = dataclasses.replace(first["clearcoat"], before=80)  # warm-started
    assert starts.inconclusive(list(first.values()), first["principled"]) is first["clearcoat"]
    noise = {"value": float(first["clearcoat"].val_loss)}  # at its floor: no contender
    _, refined = _network_start_fakes(monkeypatch, list(first.values()), {}, noise)
    faked = starts.choose_start

    def by_tiles(views, names, **kw):  # the fake's choice, its errors over the split's tiles
        c = faked(views, names, **kw)
        picked, margins = starts.pick(c.candidates, starts.units(held, 4))
        return dataclasses.replace(c, family=picked.family, margins=margins)

    monkeypatch.setattr(starts, "choose_start", by_tiles)
    calls: list[tuple[str, bool]] = []
    monkeypatch.setattr(starts, "fit_candidate", _per_pixel(terms, calls))
    lines: list[str] = []
    _, info, _ = starts.network_start(cfg, views, path.parent / "init_x", report=lines.append)
    s = info["start"]
    assert s["family"] == "clearcoat" and s["first_choice"] == "principled"
    assert s["cross_check"]["chosen"] == "clearcoat" and s["cross_check"]["folds"] == 2
    assert [c.family for c in refined] == ["clearcoat"]
    assert len(calls) == 1 + 3 * 2 and s["seconds"] == pytest.approx(
        1.0 + s["cross_check"]["seconds"] + 3.0
    )
    assert any(line.startswith("cross-check clearcoat against principled") for line in lines)
    # off: the split's choice stands
    calls.clear()
    refined.clear()
    cfg0 = config.load(path, ["images.start=auto", "images.start_cross_folds=0"])
    _, info, _ = starts.network_start(cfg0, views, path.parent / "init_0")
    s = info["start"]
    assert s["family"] == "principled" and "cross_check" not in s and calls == []


# ------------------------------------------------------------------ a warm start's head start
def test_a_family_is_not_chosen_over_its_source_for_its_longer_fit_alone(monkeypatch):
    """images.start_catch_up: the anisotropic conductor, warm-started from the isotropic
    one, has had twice its steps and wins the split by more than the rule's tie; the
    isotropic conductor fitted as many steps further scores as well (the development
    silver) and is chosen; where it does not catch up, the richer family stays.  Only the
    chosen family's sources are fitted further, only while they had fewer steps, and a
    family fitted without a warm start has no head start to make up."""
    from neural_brdf.inverse import starts

    rng = np.random.default_rng(4)
    unit = np.repeat(np.arange(12), 16)
    base = rng.gamma(2.0, 0.0005, unit.size)
    kw = dict(mask_train=[], mask_val=[], seed=0, schedule=starts.Schedule(), unit=unit)
    cands = [
        _first("diffuse", base * 8.0),
        _first("roughconductor", base * 1.15),
        dataclasses.replace(_first("roughconductor_aniso", base), before=80),  # from it
    ]
    first, margins = starts.pick(cands, unit)
    assert first.family == "roughconductor_aniso" and not margins["roughconductor"]["tied"]
    calls: list[str] = []
    caught_up = {"roughconductor": base * 1.002}
    monkeypatch.setattr(starts, "fit_candidate", _continued_to(caught_up, calls))
    seen: list[tuple[str, str]] = []
    chosen, pool, done, margins, picked = starts.catch_up(
        [], cands, progress=lambda n, by, r: seen.append((n, by)), **kw
    )
    assert calls == ["roughconductor"] and seen == [("roughconductor", "roughconductor_aniso")]
    assert chosen.family == "roughconductor" and picked == "roughconductor_aniso"
    assert margins["roughconductor"]["tied"] and done["roughconductor"]["kept"]
    assert pool[1].total_steps == pool[2].total_steps == 160 and pool[0] is cands[0]
    assert done["roughconductor"]["val_loss_before"] == cands[1].val_loss
    # a real second lobe: the conductor fitted further stays worse, and the richer wins
    calls.clear()
    stays = {"roughconductor": base * 1.14}
    monkeypatch.setattr(starts, "fit_candidate", _continued_to(stays, calls))
    chosen, pool, done, _, picked = starts.catch_up([], cands, **kw)
    assert chosen.family == picked == "roughconductor_aniso" and calls == ["roughconductor"]
    # fitted further but worse: not kept, its steps counted, and not fitted again
    calls.clear()
    worse = {"roughconductor": base * 1.3}
    monkeypatch.setattr(starts, "fit_candidate", _continued_to(worse, calls))
    chosen, pool, done, _, _ = starts.catch_up([], cands, **kw)
    assert chosen.family == "roughconductor_aniso" and calls == ["roughconductor"]
    assert not done["roughconductor"]["kept"] and pool[1].val_loss == cands[1].val_loss
    # no head start: the anisotropic family fitted from its own start
    calls.clear()
    cold = [*cands[:2], dataclasses.replace(cands[2], before=0)]
    chosen, _, done, _, _ = starts.catch_up([], cold, **kw)
    assert chosen.family == "roughconductor_aniso" and calls == [] and done == {}
    # the blend starts from both the diffuse and the conductor: both fitted further
    calls.clear()
    blend = [*cands[:2], dataclasses.replace(_first("blend", base), before=80)]
    chosen, _, done, _, _ = starts.catch_up([], blend, **kw)
    assert sorted(calls) == ["diffuse", "roughconductor"] and chosen.family == "blend"


def test_only_the_chosen_familys_sources_catch_up(monkeypatch):
    """A blend of least held-out loss, not chosen (the principled ties with it): its
    sources are not fitted further, since steps the chosen family never had would bias
    the choice the other way (a CI copper's principled, caught up with the clearcoat,
    displaced its roughconductor).  The chosen family's own sources alone catch up."""
    from neural_brdf.inverse import starts

    rng = np.random.default_rng(8)
    unit = np.repeat(np.arange(12), 16)
    base = rng.gamma(2.0, 0.0005, unit.size)
    kw = dict(mask_train=[], mask_val=[], seed=0, schedule=starts.Schedule(), unit=unit)
    cands = [
        _first("diffuse", base * 1.2),
        _first("principled", base * 1.01),
        _first("roughconductor", base * 3.0),
        dataclasses.replace(_first("blend", base), before=80),
    ]
    first, margins = starts.pick(cands, unit)
    assert first.family == "principled" and not margins["diffuse"]["tied"]
    calls: list[str] = []
    monkeypatch.setattr(starts, "fit_candidate", _continued_to({"diffuse": base * 1.004}, calls))
    chosen, pool, done, _, picked = starts.catch_up([], cands, **kw)
    assert calls == [] and done == {} and chosen.family == picked == "principled"
    assert [c.total_steps for c in pool] == [80, 80, 80, 160]


def test_choose_start_catches_a_source_up_and_records_it(monkeypatch):
    """choose_start fits the coat from the principled (its steps counted behind it),
    picks the coat, fits the principled as many steps further, and takes it when it
    scores as well: the Choice and its summary say what was picked first and what was
    fitted further; with catch_up_sources off the first pick stands."""
    from neural_brdf.inverse import starts

    train, held = _masks()
    floor = [np.random.default_rng(6).gamma(4.0, 0.00025, m.shape) for m in train]
    terms = {"principled": [1.3 * f for f in floor], "clearcoat": floor}  # 30 % worse
    calls: list[tuple[str, bool]] = []
    caught_up = {"principled": terms["clearcoat"]}
    monkeypatch.setattr(starts, "fit_candidate", _per_pixel(terms, calls, caught_up))
    kw = dict(masks=(train, held), schedule=starts.Schedule())
    choice = starts.choose_start([None], ["principled", "clearcoat"], **kw)
    assert calls == [("principled", False), ("clearcoat", True), ("principled", True)]
    assert choice.family == "principled" and choice.first_pick == "clearcoat"
    coat = next(c for c in choice.candidates if c.family == "clearcoat")
    assert coat.before == 80 and coat.total_steps == choice.chosen.total_steps == 160
    s = choice.summary()
    assert s["first_pick"] == "clearcoat" and s["caught_up"]["principled"]["kept"]
    assert s["candidates"][0]["steps_before"] == 80 and s["candidates"][0]["tied"]
    calls.clear()
    off = starts.choose_start([None], ["principled", "clearcoat"], catch_up_sources=False, **kw)
    assert off.family == "clearcoat" and off.caught_up == {} and "first_pick" not in off.summary()
    assert calls == [("principled", False), ("clearcoat", True)]

"""The pool of a textured fit grows with its field (``texture.pool_per_texel``,
docs/mitsuba.md "The pool and the field's resolution"): at least that many pairs per
texel of the R x R field, never fewer than ``data.pool_size``; null leaves
``data.pool_size`` alone; the memory check names the key before anything is drawn, and
counts it only for a teacher that may vary over the surface."""

from __future__ import annotations

import pytest

from neural_brdf import config as cfgmod
from neural_brdf import limits


def _cfg(**texture) -> cfgmod.Config:
    return cfgmod.Config.model_validate({"target": {"mitsuba": "teacher.xml"}, "texture": texture})


def test_the_pool_holds_pool_per_texel_pairs_per_texel_and_never_fewer_than_pool_size():
    small = _cfg(resolution=8, pool_per_texel=100)
    assert small.texture.pool(small.data.pool_size) == small.data.pool_size  # 6,400 < default
    big = _cfg(resolution=64, pool_per_texel=100)
    assert big.texture.pool(big.data.pool_size) == 100 * 64 * 64
    assert big.texture.pool(1 << 20) == 1 << 20  # a larger data.pool_size is kept
    off = _cfg(resolution=256, pool_per_texel=None)
    assert off.texture.pool(off.data.pool_size) == off.data.pool_size
    # the default grows the default field's pool beyond data.pool_size's default
    d = _cfg()
    assert d.texture.pool(d.data.pool_size) == d.texture.pool_per_texel * d.texture.resolution**2
    assert d.texture.pool(d.data.pool_size) > d.data.pool_size


def test_the_memory_check_names_pool_per_texel_for_a_textured_teacher(monkeypatch):
    cfg = _cfg(resolution=1024)  # 2048 pairs per texel of 1024^2: 2^31 pairs
    sizes = dict(cfgmod.sizes(cfg))
    assert sizes["texture.pool_per_texel"] == cfg.texture.pool(cfg.data.pool_size) * (
        cfgmod.PAIR_BYTES
    )
    monkeypatch.setenv(limits.ENV_LIMIT, "64G")
    with pytest.raises(limits.TooLarge, match=r"^config: texture\.pool_per_texel: would need"):
        cfgmod.check_sizes(cfg)
    cfgmod.check_sizes(_cfg(resolution=1024, pool_per_texel=None))  # data.pool_size alone
    # a homogeneous target never reads it
    assert "texture.pool_per_texel" not in dict(cfgmod.sizes(cfgmod.Config()))


def test_the_memory_check_names_project_pairs(monkeypatch):
    # a texel's projection pairs are drawn and solved at once: 2e9 of them trained first
    # and then failed with a line that named no key, leaving an unfinished run
    monkeypatch.setenv(limits.ENV_LIMIT, "64G")
    huge = ["target.mitsuba=t.xml", "texture.project=8", "texture.project_pairs=2000000000"]
    with pytest.raises(limits.TooLarge, match=r"texture\.project_pairs: would need"):
        cfgmod.load(None, huge)  # the loader checks the sizes, before anything runs
    cfgmod.load(None, ["target.mitsuba=t.xml", "texture.project=8"])
    assert "texture.project_pairs" not in dict(cfgmod.sizes(_cfg()))  # no projection


@pytest.mark.parametrize("value", ["0", "-5", "1.5", "many"])
def test_a_bad_pool_per_texel_is_refused(value):
    with pytest.raises(cfgmod.ConfigError, match="texture.pool_per_texel"):
        cfgmod.load(None, ["target.mitsuba=t.xml", f"texture.pool_per_texel={value}"])


def test_a_homogeneous_teacher_is_not_refused_for_a_pool_it_never_draws(tmp_path, monkeypatch):
    """A teacher without a texture reads data.pool_size alone, so the memory check does
    not count (nor refuse) the textured pool for it."""
    plain = tmp_path / "plain.xml"
    plain.write_text('<bsdf version="3.0.0" type="roughplastic"/>')
    mapped = tmp_path / "mapped.xml"
    mapped.write_text(
        '<bsdf version="3.0.0" type="diffuse"><texture type="checkerboard" name="reflectance"/>'
        "</bsdf>"
    )
    texture = {"resolution": 1024}
    homogeneous = cfgmod.Config.model_validate(
        {"target": {"mitsuba": str(plain)}, "texture": texture}
    )
    textured = cfgmod.Config.model_validate(
        {"target": {"mitsuba": str(mapped)}, "texture": texture}
    )
    assert "texture.pool_per_texel" not in dict(cfgmod.sizes(homogeneous))
    assert "texture.pool_per_texel" in dict(cfgmod.sizes(textured))
    monkeypatch.setenv(limits.ENV_LIMIT, "64G")
    cfgmod.check_sizes(homogeneous)
    with pytest.raises(limits.TooLarge, match=r"texture\.pool_per_texel"):
        cfgmod.check_sizes(textured)

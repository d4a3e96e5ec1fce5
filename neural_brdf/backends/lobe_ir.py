"""The stored sampling lobe (:mod:`neural_brdf.fileformat.lobe`) as lowered programs for the
back ends.

    from neural_brdf.backends import lobe_ir
    shape = {"alpha_x": 0.2, "alpha_y": 0.4, "weight": 0.6, "retro": False}
    pdf = lobe.pdf_program(**shape)      # inputs wi, wo -> output pdf
    smp = lobe.sample_program(**shape)   # inputs wi, u1, u2 -> wo, pdf

The mixture of :mod:`neural_brdf.fileformat.lobe`: a cosine-weighted hemisphere (share 1 - w) and
a GGX visible-normal lobe of roughness (ax, ay) reflected about the sampled normal (share
w; a Beckmann lobe with ``distribution="beckmann"``), turned by pi about the normal for
a retro lobe.  With a per-incidence ``table``, ax, ay and w are interpolated linearly in
cos theta_i between its nodes.  It is written once
here with the instruction builder of :mod:`neural_brdf.graph` and rendered by every code
back end, like the network itself.

    pdf(wo) = (1 - w) cos(theta_o) / pi + w D_wi(m) / (4 (v . m)),  m = normalize(wi + v)
    v       = wo (mirror lobe), or (-wo_x, -wo_y, wo_z) (retro lobe)
    D_wi(m) = G1(wi) max(0, wi . m) D(m) / wi_z           (Heitz 2018, eq. 1)
    D(m)    = 1 / (pi ax ay (m_x^2 / ax^2 + m_y^2 / ay^2 + m_z^2)^2)   (GGX, Walter 2007)
    G1(wi)  = 2 wi_z / (wi_z + sqrt(ax^2 wi_x^2 + ay^2 wi_y^2 + wi_z^2))   (Smith, GGX)

0 when wi or wo is at or below the horizon.  ``sample`` draws the GGX branch when
u1 < w (Heitz 2018, "Sampling the GGX Distribution of Visible Normals", JCGT 7(4),
listing 1, with u2; turned for a retro lobe) and the cosine branch otherwise (u2 ->
r = sqrt(u2.x), phi = 2 pi u2.y); it returns the sampled wo and pdf(wo) computed by the
same instructions as ``pdf`` (0 when wo is below the horizon).

Both normalise their directions first, as the exported graph does for f
(:func:`neural_brdf.train.model.unit_or_invalid`, the same operations): pdf(k wi, k' wo)
is pdf(wi, wo) for k, k' > 0 (to float32 rounding), and a direction with a NaN, an
infinity or zero length gives pdf 0; ``sample`` of such a wi returns wo = (0, 0, -1)
(below the horizon) and pdf 0, a rejected sample, and so does ``sample`` given a random
number (u1, u2.x or u2.y) that is not finite or not in [0, 1) (1 included).
"""

from __future__ import annotations

import math

from neural_brdf.graph import Builder, Program


class V:
    """An instruction id with arithmetic operators, for writing programs by hand."""

    __slots__ = ("b", "i")

    def __init__(self, b: Builder, i: int):
        self.b, self.i = b, i

    def _id(self, x) -> int:
        return x.i if isinstance(x, V) else self.b.scalar(x)

    def _op(self, op, *xs) -> V:
        return V(self.b, self.b.emit(op, *(self._id(x) for x in xs)))

    def __add__(self, o):
        return self._op("add", self, o)

    def __radd__(self, o):
        return self._op("add", o, self)

    def __sub__(self, o):
        return self._op("sub", self, o)

    def __rsub__(self, o):
        return self._op("sub", o, self)

    def __mul__(self, o):
        return self._op("mul", self, o)

    def __rmul__(self, o):
        return self._op("mul", o, self)

    def __truediv__(self, o):
        return self._op("div", self, o)

    def __rtruediv__(self, o):
        return self._op("div", o, self)

    def __neg__(self):
        return self._op("neg", self)

    def __gt__(self, o):
        return self._op("gt", self, o)

    def __lt__(self, o):
        return self._op("lt", self, o)

    def __and__(self, o):
        return self._op("and", self, o)

    def f(self, op: str) -> V:
        return self._op(op, self)


def _select(c: V, a, b) -> V:
    return c._op("select", c, a, b)


def _max(a: V, b) -> V:
    return a._op("max", a, b)


def _dot(a, b) -> V:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _normalize(v):
    inv = 1.0 / _dot(v, v).f("sqrt")
    return [c * inv for c in v]


def _unit_or_invalid(b: Builder, w: list[V]) -> tuple[list[V], V]:
    """(unit vector, valid) for any float direction, by the operations of the exported
    graph (:func:`neural_brdf.train.model.unit_or_invalid`): valid when the three
    components are finite and not all zero; scaled by the largest absolute component,
    then divided by its norm; an invalid direction becomes +z (its result is then
    replaced by the caller)."""
    b.hint = "unit"
    bad = [c._op("or", c.f("isnan"), c.f("isinf")) for c in w]
    ok = bad[0]._op("not", bad[0]._op("or", bad[0]._op("or", bad[0], bad[1]), bad[2]))
    a = [_select(ok, c, 0.0).f("abs") for c in w]
    m = _max(_max(a[0], a[1]), a[2])
    ok = ok & (m > 0.0)
    u = [_select(ok, c, 0.0) / _select(ok, m, 1.0) for c in w]
    n = (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).f("sqrt")
    inv = _select(ok, n, 1.0)
    return [_select(ok, c / inv, z) for c, z in zip(u, (0.0, 0.0, 1.0), strict=True)], ok


def _random_numbers(b: Builder, u1: V, u2: list[V]) -> tuple[V, list[V], V]:
    """(u1, u2, valid): valid where u1, u2.x and u2.y are all finite and in [0, 1) (a
    NaN fails every comparison, but the test is also a bit test, isnan and isinf, which
    -ffast-math does not fold away and GLSL may not assume false); each number is
    replaced by 0 where they are not, so that no NaN flows through the sampler."""
    b.hint = "rnd"  # (not "u": its temporaries u1, u2 would shadow the inputs)
    us = [u1, *u2]
    good = [
        u._op("not", u._op("or", u.f("isnan"), u.f("isinf"))) & u._op("ge", u, 0.0) & (u < 1.0)
        for u in us
    ]
    ok = good[0] & good[1] & good[2]
    safe = [_select(ok, u, 0.0) for u in us]
    return safe[0], safe[1:], ok


def _vec(b: Builder, name: str, n: int) -> list[V]:
    b.hint = name
    return [V(b, b.input(name, k)) for k in range(n)]


def _turn(w: list[V]) -> list[V]:
    """A half turn about the normal: (x, y, z) -> (-x, -y, z)."""
    return [-w[0], -w[1], w[2]]


def _interp(c: V, xs: list[float], ys: list[float]):
    """ys interpolated linearly at c over the ascending nodes xs, clamped at the ends:
    y0 + sum_k clamp((c - x_{k-1}) / (x_k - x_{k-1}), 0, 1) (y_k - y_{k-1})."""
    y = float(ys[0])
    for k in range(1, len(xs)):
        dy = float(ys[k]) - float(ys[k - 1])
        if dy != 0.0:
            t = (c - float(xs[k - 1])) * (1.0 / (float(xs[k]) - float(xs[k - 1])))
            y = y + c._op("min", _max(t, 0.0), 1.0) * dy
    return y


def _params(b: Builder, wi: list[V], ax, ay, weight, table) -> tuple:
    """(alpha_x, alpha_y, weight): the lobe's constants, or with a per-incidence table
    expressions of cos theta_i (neural_brdf.fileformat.lobe.at)."""
    if not table:
        return ax, ay, weight
    b.hint = "lobe_table"
    c = table["cos_theta"]
    return tuple(_interp(wi[2], c, table[k]) for k in ("alpha_x", "alpha_y", "weight"))


def _uses_ggx(weight, table) -> bool:
    return (max(table["weight"]) if table else weight) > 0.0


def _pdf(
    b: Builder,
    wi: list[V],
    wo: list[V],
    ax,
    ay,
    weight,
    retro: bool,
    table=None,
    distribution: str = "ggx",
) -> V:
    uses_ggx = _uses_ggx(weight, table)
    ax, ay, weight = _params(b, wi, ax, ay, weight, table)
    b.hint = "pdf"
    valid = (wi[2] > 0.0) & (wo[2] > 0.0)
    p = (1.0 - weight) * (1.0 / math.pi) * wo[2]
    if uses_ggx:
        v = _turn(wo) if retro else wo
        m = _normalize([wi[k] + v[k] for k in range(3)])
        dot_om = _dot(v, m)
        dot_im = _max(_dot(wi, m), 0.0)
        if distribution == "beckmann":
            # D = exp(-(m_x^2 / ax^2 + m_y^2 / ay^2) / m_z^2) / (pi ax ay m_z^4) and
            # Lambda(a) = (erf(a) - 1) / 2 + exp(-a^2) / (2 a sqrt(pi)), a = 1 / (alpha
            # tan theta) (Walter et al. 2007, eqs. 25 and 27)
            mz = _max(m[2], 1e-6)
            e = (m[0] * m[0] * (1.0 / (ax * ax)) + m[1] * m[1] * (1.0 / (ay * ay))) / (mz * mz)
            d = _select(
                m[2] > 1e-6, (-e).f("exp") / (math.pi * ax * ay * (mz * mz) * (mz * mz)), 0.0
            )
            a2 = ((ax * ax) * (wi[0] * wi[0]) + (ay * ay) * (wi[1] * wi[1])) / (wi[2] * wi[2])
            a = 1.0 / _max(a2, 1e-30).f("sqrt")
            lam = 0.5 * (a.f("erf") - 1.0) + (-(a * a)).f("exp") / (a * (2.0 * math.sqrt(math.pi)))
            g1 = 1.0 / (1.0 + lam)
        else:
            t = m[0] * m[0] * (1.0 / (ax * ax)) + m[1] * m[1] * (1.0 / (ay * ay)) + m[2] * m[2]
            d = 1.0 / (math.pi * ax * ay * t * t)
            s = (ax * ax) * (wi[0] * wi[0]) + (ay * ay) * (wi[1] * wi[1]) + wi[2] * wi[2]
            g1 = 2.0 * wi[2] / (wi[2] + s.f("sqrt"))
        d_visible = g1 * dot_im * d / wi[2]
        ggx = _select(dot_om > 0.0, d_visible / (4.0 * dot_om), 0.0)
        p = p + weight * ggx
    return _select(valid, p, 0.0)


def pdf_program(
    *,
    alpha_x: float,
    alpha_y: float,
    weight: float,
    retro: bool = False,
    table: dict | None = None,
    distribution: str = "ggx",
) -> Program:
    """Inputs ``wi``, ``wo`` (3 columns) -> output ``pdf`` (solid-angle density of wo)."""
    b = Builder()
    wi, ok_i = _unit_or_invalid(b, _vec(b, "wi", 3))
    wo, ok_o = _unit_or_invalid(b, _vec(b, "wo", 3))
    p = _pdf(b, wi, wo, alpha_x, alpha_y, weight, retro, table, distribution)
    p = _select(ok_i & ok_o, p, 0.0)
    return b.finish({"wi": 3, "wo": 3}, {"pdf": [p.i]})


def _ggx_vndf(b: Builder, wi: list[V], u: list[V], ax, ay) -> list[V]:
    """A visible normal of GGX(ax, ay) seen from wi (Heitz 2018, JCGT, listing 1)."""
    b.hint = "vndf"
    vh = _normalize([ax * wi[0], ay * wi[1], wi[2]])  # the hemisphere configuration
    lensq = vh[0] * vh[0] + vh[1] * vh[1]
    has_xy = lensq > 0.0
    inv = 1.0 / _max(lensq, 1e-30).f("sqrt")
    t1 = [_select(has_xy, -vh[1] * inv, 1.0), _select(has_xy, vh[0] * inv, 0.0), None]
    # T2 = cross(Vh, T1) with T1_z = 0
    t2 = [-vh[2] * t1[1], vh[2] * t1[0], vh[0] * t1[1] - vh[1] * t1[0]]
    r = u[0].f("sqrt")
    phi = 2.0 * math.pi * u[1]
    p1 = r * phi.f("cos")
    p2 = r * phi.f("sin")
    s = 0.5 * (1.0 + vh[2])
    p2 = (1.0 - s) * _max(1.0 - p1 * p1, 0.0).f("sqrt") + s * p2
    pz = _max(1.0 - p1 * p1 - p2 * p2, 0.0).f("sqrt")
    nh = [
        p1 * t1[0] + p2 * t2[0] + pz * vh[0],
        p1 * t1[1] + p2 * t2[1] + pz * vh[1],
        p2 * t2[2] + pz * vh[2],
    ]
    return _normalize([ax * nh[0], ay * nh[1], _max(nh[2], 0.0)])


# Bisection steps of the Beckmann visible-slope sampler: the interval [-6, 6] shrinks
# to 12 / 2^20 ~ 1e-5 in slope, below float32's resolution of the directions it makes.
BISECTIONS = 20


def _bisect(fn, target: V, lo: V, hi) -> V:
    """x in [lo, hi] with fn(x) = target, fn increasing: BISECTIONS halvings."""
    for _ in range(BISECTIONS):
        mid = (lo + hi) * 0.5
        below = fn(mid) < target
        lo, hi = _select(below, mid, lo), _select(below, hi, mid)
    return (lo + hi) * 0.5


def _beckmann_vndf(b: Builder, wi: list[V], u: list[V], ax, ay) -> list[V]:
    """A visible normal of Beckmann(ax, ay) seen from wi.  Heitz & d'Eon 2014: stretch wi
    to unit roughness; with it at polar angle t and azimuth 0 the visible slopes have the
    density (cos t - x sin t) exp(-x^2 - y^2) / pi on x < cot t, so y ~ N(0, 1/2) and x
    has the (unnormalised) CDF C(x) = cos t (1 + erf x) / 2 + sin t exp(-x^2) / (2
    sqrt(pi)).  Both are inverted by bisection on [-6, 6] (the tails beyond hold < 1e-16
    of the mass), u.x for x and u.y for y; the slopes are turned to wi's azimuth and
    unstretched."""
    b.hint = "vndf"
    ws = _normalize([ax * wi[0], ay * wi[1], wi[2]])
    ct = ws[2]
    st = _max(1.0 - ct * ct, 0.0).f("sqrt")
    hi = ct._op("min", ct / _max(st, 1e-30), 6.0)  # x < cot t

    def cdf(x: V) -> V:
        return ct * (0.5 * (1.0 + x.f("erf"))) + st * (-(x * x)).f("exp") * (
            0.5 / math.sqrt(math.pi)
        )

    x = _bisect(cdf, u[0] * cdf(hi), V(b, b.scalar(-6.0)), hi)
    y = _bisect(lambda t: t.f("erf"), 2.0 * u[1] - 1.0, V(b, b.scalar(-6.0)), 6.0)
    r2 = ws[0] * ws[0] + ws[1] * ws[1]
    has_xy = r2 > 0.0
    inv = 1.0 / _max(r2, 1e-30).f("sqrt")
    cp, sp = _select(has_xy, ws[0] * inv, 1.0), _select(has_xy, ws[1] * inv, 0.0)
    sx, sy = cp * x - sp * y, sp * x + cp * y
    return _normalize([-(ax * sx), -(ay * sy), 1.0])


def sample_program(
    *,
    alpha_x: float,
    alpha_y: float,
    weight: float,
    retro: bool = False,
    table: dict | None = None,
    distribution: str = "ggx",
) -> Program:
    """Inputs ``wi`` (3), ``u1`` (1), ``u2`` (2) -> outputs ``wo`` (3) and ``pdf``."""
    b = Builder()
    wi, ok = _unit_or_invalid(b, _vec(b, "wi", 3))
    u1, u2, u_ok = _random_numbers(b, _vec(b, "u1", 1)[0], _vec(b, "u2", 2))
    ok = ok & u_ok
    b.hint = "cosine"
    r = u2[0].f("sqrt")
    phi = 2.0 * math.pi * u2[1]
    wo = [r * phi.f("cos"), r * phi.f("sin"), _max(1.0 - u2[0], 0.0).f("sqrt")]
    if _uses_ggx(weight, table):
        ax, ay, w = _params(b, wi, alpha_x, alpha_y, weight, table)
        vndf = _beckmann_vndf if distribution == "beckmann" else _ggx_vndf
        m = vndf(b, wi, u2, ax, ay)
        b.hint = "mirror"
        k = 2.0 * _dot(wi, m)
        v = [k * m[j] - wi[j] for j in range(3)]
        v = _turn(v) if retro else v
        pick = u1 < w
        wo = [_select(pick, v[j], wo[j]) for j in range(3)]
    # an invalid wi or random number: a rejected sample below the horizon
    wo = [_select(ok, c, z) for c, z in zip(wo, (0.0, 0.0, -1.0), strict=True)]
    # pdf(wi, wo) by pdf_program's instructions, wo normalised as there (a sampled wo is
    # a unit vector up to rounding), so that the two agree bit for bit
    uo, ok_o = _unit_or_invalid(b, wo)
    p = _pdf(b, wi, uo, alpha_x, alpha_y, weight, retro, table, distribution)
    p = _select(ok & ok_o, p, 0.0)
    return b.finish({"wi": 3, "u1": 1, "u2": 2}, {"wo": [v.i for v in wo], "pdf": [p.i]})

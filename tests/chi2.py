"""Chi-square goodness-of-fit test of a direction sampler against its density.

Written for the analytic BRDFs (numpy and scipy only), in the spirit of Mitsuba 3's
``chi2.py``: draw many directions with the sampler, histogram them on the sphere,
integrate the claimed density over the same cells with a deterministic quadrature, and
ask Pearson's chi-square test whether the counts could come from that density.

    result = chi2.chi2_test(sample_fn, pdf_fn, name="lambertian-wi45")
    assert result.passed, result.summary()

Binning.  The **whole sphere** is binned, since a BRDF's ``pdf`` is a density over the
whole sphere (samples may land below the horizon, where ``eval`` is 0).  Cells are
equal-area: uniform in ``cos(theta)`` in [-1, 1] and in ``phi`` in [-pi, pi], since
``dw = d(cos theta) d(phi)``.  The number of ``cos(theta)`` rows is even, so that the
horizon is a cell edge, never inside a cell: densities with a kink or jump there (a
cosine lobe) are then smooth within every cell.

Quadrature.  Each cell's probability is the integral of the pdf over the cell, by
tensor Gauss-Legendre quadrature in (cos theta, phi), refined adaptively: a (sub)cell
is split 2 x 2 until the split changes its estimate by less than a tenth of the
expected count's standard deviation (scaled down by 2 per level).  Cells whose count
then lies more than 3 standard deviations from the quadrature are integrated again on a
fixed 16 x 16 subgrid with 6 x 6 nodes each, so that a lobe narrower than the adaptive
nodes' spacing is not mistaken for a sampling error.  Everything is deterministic for a
given seed; cells that did not converge within ``max_depth`` levels are reported.

Decision.  Cells expecting fewer than 5 samples are pooled (in order of increasing
expectation) so that every bin expects at least 5.  The p-value of the statistic is
compared with the Sidak-corrected level ``1 - (1 - significance)^(1 / test_count)``.
The test fails at once, whatever the statistic, when the pdf is negative or NaN
anywhere it was evaluated, when it integrates to more than 1 + 1e-3, when the sampler
returns a non-finite or non-unit direction, or when samples land in a cell where the
pdf integrates to exactly 0.  On failure the tables (observed and expected counts per
cell) are written to ``dump_dir``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import stats

# A sampler maps uniform variates u (N, 2) in [0, 1) to unit directions (N, 3);
# a density maps directions (M, 3) to pdf values (M,) w.r.t. solid angle.
SampleFn = Callable[[np.ndarray], np.ndarray]
PdfFn = Callable[[np.ndarray], np.ndarray]

MIN_EXPECTED = 5.0  # Pearson's rule of thumb: pool cells expecting fewer samples
MASS_LIMIT = 1.0 + 1e-3  # a density may not integrate to more than this
UNIT_TOL = 1e-6  # |wo| must be 1 to this (float64 samplers)
CHUNK = 1 << 19  # pdf evaluations per call (bounds memory)
RECHECK_SIGMA = 3.0  # cells this many standard deviations off are re-integrated ...
RECHECK_MAX = 512  # ... at most this many, the worst first


# --------------------------------------------------------------------------- grid
@dataclass(frozen=True)
class SphereGrid:
    """Equal-area cells: ``n_z`` rows uniform in cos(theta), ``n_phi`` columns in phi."""

    n_z: int = 64
    n_phi: int = 128

    def __post_init__(self):
        if self.n_z % 2:
            raise ValueError(f"n_z: must be even so the horizon is a cell edge, got {self.n_z}")

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_z, self.n_phi)

    @property
    def dz(self) -> float:
        return 2.0 / self.n_z

    @property
    def dphi(self) -> float:
        return 2.0 * math.pi / self.n_phi

    def cell_index(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row (cos theta) and column (phi) of each direction (N, 3)."""
        z = np.clip(w[:, 2], -1.0, 1.0)
        phi = np.arctan2(w[:, 1], w[:, 0])
        iz = np.clip(np.floor((z + 1.0) / self.dz).astype(np.int64), 0, self.n_z - 1)
        ip = np.clip(np.floor((phi + math.pi) / self.dphi).astype(np.int64), 0, self.n_phi - 1)
        return iz, ip

    def histogram(self, w: np.ndarray) -> np.ndarray:
        iz, ip = self.cell_index(w)
        flat = np.bincount(iz * self.n_phi + ip, minlength=self.n_z * self.n_phi)
        return flat.reshape(self.shape).astype(np.float64)


def _direction(z: np.ndarray, phi: np.ndarray) -> np.ndarray:
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


# --------------------------------------------------------------------------- quadrature
@dataclass
class Quadrature:
    """Probability per cell, ``mass[iz, ip]`` = integral of the pdf over the cell."""

    mass: np.ndarray
    pdf_min: float  # smallest pdf value seen at any node (NaN if one was NaN)
    unconverged: int  # subcells still refining when max_depth was reached
    evaluations: int

    @property
    def total(self) -> float:
        return float(self.mass.sum())


def _eval_pdf(pdf_fn: PdfFn, w: np.ndarray) -> np.ndarray:
    out = np.empty(len(w))
    for s in range(0, len(w), CHUNK):
        out[s : s + CHUNK] = np.asarray(pdf_fn(w[s : s + CHUNK]), dtype=np.float64).reshape(-1)
    return out


def integrate_cells(
    pdf_fn: PdfFn,
    grid: SphereGrid,
    *,
    n_samples: float = 1e6,
    order: int = 4,
    max_depth: int = 6,
    rel_tol: float = 0.1,
    max_active: int = 1 << 15,
) -> Quadrature:
    """Adaptive tensor Gauss-Legendre quadrature of ``pdf_fn`` over every grid cell.

    A subcell at refinement level ``d`` is accepted once splitting it 2 x 2 changes its
    estimate by less than ``rel_tol * sqrt(max(E, 1)) / n_samples / 2^d``, where ``E``
    is the expected count of its whole grid cell for ``n_samples`` samples; that keeps
    the quadrature error well below the sampling noise the test can resolve.
    """
    x, wts = np.polynomial.legendre.leggauss(order)
    x, wts = 0.5 * (x + 1.0), 0.5 * wts  # nodes and weights on [0, 1]
    wz, wp = np.meshgrid(wts, wts, indexing="ij")
    node_w = (wz * wp).reshape(-1)  # (order^2,)
    xz, xp = np.meshgrid(x, x, indexing="ij")
    xz, xp = xz.reshape(-1), xp.reshape(-1)

    stats_ = {"min": math.inf, "evals": 0}

    def estimate(z0, dz, p0, dp):
        """Gauss-Legendre estimate of the mass of each (sub)cell; arrays of shape (C,)."""
        z = z0[:, None] + dz[:, None] * xz[None, :]
        p = p0[:, None] + dp[:, None] * xp[None, :]
        vals = _eval_pdf(pdf_fn, _direction(z.reshape(-1), p.reshape(-1))).reshape(z.shape)
        stats_["evals"] += vals.size
        if np.isnan(vals).any():
            stats_["min"] = math.nan
        elif not math.isnan(stats_["min"]):
            stats_["min"] = min(stats_["min"], float(vals.min()))
        return (vals * node_w[None, :]).sum(-1) * dz * dp

    iz, ip = np.meshgrid(np.arange(grid.n_z), np.arange(grid.n_phi), indexing="ij")
    cell = (iz * grid.n_phi + ip).reshape(-1)  # base-cell id of each subcell
    z0 = -1.0 + grid.dz * iz.reshape(-1).astype(np.float64)
    p0 = -math.pi + grid.dphi * ip.reshape(-1).astype(np.float64)
    dz = np.full(z0.shape, grid.dz)
    dp = np.full(z0.shape, grid.dphi)
    est = estimate(z0, dz, p0, dp)
    base = est.copy()  # coarse estimate, sets the tolerance
    tol_cell = rel_tol * np.sqrt(np.maximum(base * n_samples, 1.0)) / n_samples
    mass = np.zeros(grid.n_z * grid.n_phi)
    unconverged = 0

    for depth in range(max_depth + 1):
        # split every active subcell 2 x 2: children k = 2 * a + b
        hz, hp = 0.5 * dz, 0.5 * dp
        cz0 = np.concatenate([z0, z0, z0 + hz, z0 + hz])
        cp0 = np.concatenate([p0, p0 + hp, p0, p0 + hp])
        chz = np.concatenate([hz] * 4)
        chp = np.concatenate([hp] * 4)
        child = estimate(cz0, chz, cp0, chp).reshape(4, -1)
        refined = child.sum(0)
        if math.isnan(stats_["min"]):
            break
        ok = np.abs(refined - est) <= tol_cell[cell] / 2.0**depth
        last = depth == max_depth or 4 * int((~ok).sum()) > max_active
        if last:
            unconverged = int((~ok).sum())
            ok[:] = True
        np.add.at(mass, cell[ok], refined[ok])
        if ok.all():
            break
        keep = np.tile(~ok, 4)
        z0, p0, dz, dp = cz0[keep], cp0[keep], chz[keep], chp[keep]
        cell = np.tile(cell, 4)[keep]
        est = child.reshape(-1)[keep]

    return Quadrature(mass.reshape(grid.shape), stats_["min"], unconverged, stats_["evals"])


def integrate_cells_fine(
    pdf_fn: PdfFn, grid: SphereGrid, cells: np.ndarray, *, sub: int = 16, order: int = 6
) -> tuple[np.ndarray, float]:
    """Mass of the given flat cell indices on a ``sub x sub`` subgrid of each cell with
    ``order``-point Gauss-Legendre per subcell (non-adaptive).  Returns (mass, pdf_min)."""
    x, wts = np.polynomial.legendre.leggauss(order)
    t = (np.arange(sub)[:, None] + 0.5 * (x[None, :] + 1.0)).reshape(-1) / sub  # (sub*order,)
    w = np.tile(0.5 * wts, sub) / sub
    wz, wp = np.meshgrid(w, w, indexing="ij")
    tz, tp = np.meshgrid(t, t, indexing="ij")
    w2, tz, tp = (wz * wp).reshape(-1), tz.reshape(-1), tp.reshape(-1)
    mass = np.empty(len(cells))
    pdf_min = math.inf
    per = max(1, CHUNK // len(w2))
    for s in range(0, len(cells), per):
        iz, ip = np.divmod(cells[s : s + per], grid.n_phi)
        z = -1.0 + grid.dz * (iz[:, None] + tz[None, :])
        p = -math.pi + grid.dphi * (ip[:, None] + tp[None, :])
        vals = _eval_pdf(pdf_fn, _direction(z.reshape(-1), p.reshape(-1))).reshape(z.shape)
        pdf_min = math.nan if np.isnan(vals).any() else min(pdf_min, float(vals.min()))
        mass[s : s + per] = (vals * w2[None, :]).sum(-1) * grid.dz * grid.dphi
    return mass, pdf_min


def sphere_integral(pdf_fn: PdfFn, *, grid: SphereGrid | None = None, **kw) -> float:
    """Integral of a density over the whole sphere (deterministic adaptive quadrature)."""
    return integrate_cells(pdf_fn, grid or SphereGrid(32, 64), **kw).total


# --------------------------------------------------------------------------- the test
@dataclass
class Chi2Result:
    name: str
    passed: bool
    p_value: float
    statistic: float
    dof: int
    significance: float  # after the Sidak correction
    pdf_mass: float  # integral of the pdf over the sphere
    pooled_in: int = 0  # low-expectation cells pooled ...
    pooled_out: int = 0  # ... into this many bins
    messages: list[str] = field(default_factory=list)
    dump_path: Path | None = None

    def summary(self) -> str:
        head = (
            f"chi2 {self.name}: {'passed' if self.passed else 'FAILED'}; "
            f"statistic {self.statistic:.1f}, dof {self.dof}, p {self.p_value:.3g} "
            f"(level {self.significance:.3g}); pdf mass {self.pdf_mass:.6f}"
        )
        lines = [head] + ["  " + m for m in self.messages]
        if self.dump_path is not None:
            lines.append(f"  tables written to {self.dump_path}")
        return "\n".join(lines)


def pool(observed: np.ndarray, expected: np.ndarray, min_expected: float = MIN_EXPECTED):
    """Pool cells (by increasing expectation) into bins expecting >= ``min_expected``.

    Returns (observed_bins, expected_bins, cells_pooled, bins_made).  Cells with zero
    expectation are not bins at all (the caller rejects samples found there).
    """
    keep = expected > 0
    o, e = observed[keep], expected[keep]
    order = np.argsort(e, kind="stable")
    o, e = o[order], e[order]
    small = int(np.searchsorted(e, min_expected))  # cells expecting < min_expected
    bins_o, bins_e = list(o[small:]), list(e[small:])
    acc_o = acc_e = 0.0
    extra = 0
    pooled_o, pooled_e = [], []
    for oi, ei in zip(o[:small], e[:small]):
        acc_o += oi
        acc_e += ei
        if acc_e >= min_expected:
            pooled_o.append(acc_o)
            pooled_e.append(acc_e)
            acc_o = acc_e = 0.0
    if acc_e > 0:  # a remainder joins a pooled bin
        if pooled_e:
            pooled_o[-1] += acc_o
            pooled_e[-1] += acc_e
        elif bins_e:
            bins_o[0] += acc_o
            bins_e[0] += acc_e
            extra = 1
        else:
            pooled_o.append(acc_o)
            pooled_e.append(acc_e)
    made = len(pooled_e) + extra
    return (np.array(pooled_o + bins_o), np.array(pooled_e + bins_e), small, made)


def sidak(significance: float, test_count: int) -> float:
    return 1.0 - (1.0 - significance) ** (1.0 / max(int(test_count), 1))


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "chi2"


def chi2_test(
    sample_fn: SampleFn,
    pdf_fn: PdfFn,
    *,
    name: str = "chi2",
    n_samples: int = 1_000_000,
    grid: SphereGrid | None = None,
    seed: int = 0,
    significance: float = 0.01,
    test_count: int = 1,
    dump_dir: str | Path | None = None,
    quadrature: dict | None = None,
) -> Chi2Result:
    """Pearson's chi-square test of ``sample_fn`` against ``pdf_fn`` on the whole sphere.

    ``sample_fn(u)`` receives ``n_samples`` uniform variates (N, 2) in [0, 1) from a
    numpy generator seeded with ``seed`` and returns directions (N, 3).
    """
    grid = grid or SphereGrid()
    level = sidak(significance, test_count)
    messages: list[str] = []
    fail = False

    u = np.random.default_rng(seed).random((n_samples, 2))
    wo = np.asarray(sample_fn(u), dtype=np.float64).reshape(n_samples, 3)
    finite = np.isfinite(wo).all(-1)
    if not finite.all():
        messages.append(f"sampler returned {int((~finite).sum())} non-finite directions")
        fail = True
    norm_err = np.abs(np.linalg.norm(wo[finite], axis=-1) - 1.0)
    if norm_err.size and norm_err.max() > UNIT_TOL:
        messages.append(
            f"sampler returned non-unit directions (max | |wo| - 1 | = {norm_err.max():.3g})"
        )
        fail = True
    observed = grid.histogram(wo[finite])

    quad = integrate_cells(pdf_fn, grid, n_samples=n_samples, **(quadrature or {}))
    expected = quad.mass * n_samples
    if math.isnan(quad.pdf_min):
        messages.append("pdf is NaN somewhere on the sphere")
        fail = True
    elif quad.pdf_min < 0:
        messages.append(f"pdf is negative somewhere on the sphere (min {quad.pdf_min:.3g})")
        fail = True
    if not quad.total <= MASS_LIMIT:
        messages.append(f"pdf integrates to {quad.total:.6f} > {MASS_LIMIT} over the sphere")
        fail = True
    if quad.unconverged:
        messages.append(f"quadrature: {quad.unconverged} subcells unconverged at max depth")

    # Cells whose count is far from the quadrature are integrated again on a fine fixed
    # subgrid, so that a lobe narrower than the adaptive nodes' spacing is not blamed on
    # the sampler (a true mismatch stays a mismatch: the fine integral is just as valid).
    if not fail:
        far = np.abs(observed - expected) > RECHECK_SIGMA * np.sqrt(np.maximum(expected, 1.0))
        cells = np.flatnonzero(far.reshape(-1))
        if cells.size:
            gap = np.abs(observed - expected).reshape(-1)[cells]
            cells = cells[np.argsort(gap)[::-1][:RECHECK_MAX]]
            fine, fine_min = integrate_cells_fine(pdf_fn, grid, cells)
            expected.reshape(-1)[cells] = fine * n_samples
            messages.append(f"re-integrated {cells.size} cells on a fine subgrid")
            if not fine_min >= 0:
                messages.append(f"pdf is negative or NaN inside a cell (min {fine_min:.3g})")
                fail = True
            total = expected.sum() / n_samples
            if not total <= MASS_LIMIT:
                messages.append(f"pdf integrates to {total:.6f} > {MASS_LIMIT} over the sphere")
                fail = True

    stray = (expected <= 0) & (observed > 0)
    if stray.any():
        messages.append(
            f"{int(observed[stray].sum())} samples in {int(stray.sum())} cells "
            "where the pdf integrates to 0"
        )
        fail = True

    statistic, dof, p_value, pooled_in, pooled_out = math.nan, 0, math.nan, 0, 0
    if not fail:
        o, e, pooled_in, pooled_out = pool(observed.reshape(-1), expected.reshape(-1))
        dof = len(e) - 1
        if dof < 1:
            messages.append("too few degrees of freedom (the density fills < 2 bins)")
            fail = True
        else:
            statistic = float(((o - e) ** 2 / e).sum())
            p_value = float(stats.chi2.sf(statistic, dof))
            if pooled_in:
                messages.append(
                    f"pooled {pooled_in} cells expecting < {MIN_EXPECTED:g} "
                    f"samples into {pooled_out} bins"
                )
            if not (p_value >= level):
                messages.append(f"rejected: p-value {p_value:.3g} < level {level:.3g}")
                fail = True

    result = Chi2Result(
        name,
        not fail,
        p_value,
        statistic,
        dof,
        level,
        expected.sum() / n_samples,
        pooled_in,
        pooled_out,
        messages,
    )
    if fail and dump_dir is not None:
        result.dump_path = _dump(Path(dump_dir), name, grid, observed, expected, result)
    return result


def _dump(
    dump_dir: Path,
    name: str,
    grid: SphereGrid,
    observed: np.ndarray,
    expected: np.ndarray,
    result: Chi2Result,
) -> Path:
    """Write observed/expected tables (npz) and a readable report with the worst cells."""
    dump_dir.mkdir(parents=True, exist_ok=True)
    stem = dump_dir / _slug(name)
    z_edges = np.linspace(-1.0, 1.0, grid.n_z + 1)
    phi_edges = np.linspace(-math.pi, math.pi, grid.n_phi + 1)
    np.savez(
        stem.with_suffix(".npz"),
        observed=observed,
        expected=expected,
        cos_theta_edges=z_edges,
        phi_edges=phi_edges,
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        contrib = np.where(
            expected > 0, (observed - expected) ** 2 / expected, np.where(observed > 0, np.inf, 0.0)
        )
    worst = np.argsort(contrib.reshape(-1))[::-1][:25]
    lines = [
        result.summary().split("\n  tables")[0],
        "",
        "worst cells: cos_theta range, phi range, observed, expected, (o-e)^2/e",
    ]
    for flat in worst:
        iz, ip = divmod(int(flat), grid.n_phi)
        lines.append(
            f"  [{z_edges[iz]:+.4f}, {z_edges[iz + 1]:+.4f}]  "
            f"[{phi_edges[ip]:+.4f}, {phi_edges[ip + 1]:+.4f}]  "
            f"{observed[iz, ip]:10.0f}  {expected[iz, ip]:12.2f}  "
            f"{contrib[iz, ip]:10.2f}"
        )
    lines += ["", "row sums (cos_theta bins, low to high): observed / expected"]
    for iz in range(grid.n_z):
        lines.append(
            f"  [{z_edges[iz]:+.4f}, {z_edges[iz + 1]:+.4f}]  "
            f"{observed[iz].sum():10.0f}  {expected[iz].sum():12.2f}"
        )
    txt = stem.with_suffix(".txt")
    txt.write_text("\n".join(lines) + "\n")
    return txt

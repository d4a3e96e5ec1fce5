"""The report's verdict badges: the summary's rows (the physics and the highlight's peak)
agree with ``neural-brdf validate``'s verdict (:func:`neural_brdf.validate.passed`), and
each physics row's badge with the value and limit shown beside it.  The sections are
built from a metrics dict alone (no training): fast."""

from __future__ import annotations

import copy
from html.parser import HTMLParser
from pathlib import Path
from types import SimpleNamespace

import pytest

from neural_brdf import config, validate
from neural_brdf.viewer.report import sections
from neural_brdf.viewer.report.blocks import Table, Verdict, to_html

LIMITS = {"reciprocity": 1e-6, "min_value": 0.0, "max_albedo": 1.001}


def metrics(*, albedo=0.94, albedo_flag=True, peak=0.012, peak_flag=True) -> dict:
    """A run's metrics.json as validate writes it (the keys the sections read)."""
    return {
        "checks": {
            "reciprocity": {"value": 0.0, "limit": LIMITS["reciprocity"], "passed": True},
            "min_value": {"value": 0.004, "limit": LIMITS["min_value"], "passed": True},
            "max_albedo": {
                "value": albedo,
                "limit": LIMITS["max_albedo"],
                "passed": albedo_flag,
                "at_theta_deg": 89.99,
                "quadrature_stderr": 6e-4,
            },
        },
        "peak": {
            "value": peak,
            "limit": 0.03,
            "passed": peak_flag,
            "pairs": [
                {
                    "theta_deg": 45.0,
                    "phi_deg": 0.0,
                    "way": "normal",
                    "offset_deg": 0.0,
                    "error": 0.01,
                },
                {
                    "theta_deg": 45.0,
                    "phi_deg": 0.0,
                    "way": "normal",
                    "offset_deg": 0.1,
                    "error": 0.02,
                },
            ],
        },
        "accuracy": {"rel_rmse": 0.004},
        "training": {"steps": 1500},
        "seconds": {"train": 1.0},
    }


def fake_run(m: dict) -> SimpleNamespace:
    return SimpleNamespace(
        dir=Path("run"),
        config=config.from_dict({}),
        metrics=m,
        images=False,
        model=SimpleNamespace(textured=False),
    )


def verdicts(table: Table) -> list[tuple[str, bool]]:
    return [(str(r[0]), c.passed) for r in table.rows for c in r if isinstance(c, Verdict)]


def summary_verdicts(m: dict) -> list[tuple[str, bool]]:
    (table,) = [b for b in sections._summary(fake_run(m)) if isinstance(b, Table)]
    return verdicts(table)


def physics_rows(m: dict) -> dict[str, list]:
    (table,) = [b for b in sections._physics(fake_run(m), b"") if isinstance(b, Table)]
    return {str(r[0]): r for r in table.rows}


@pytest.mark.parametrize("peak", [0.0315, 0.012])
def test_the_summary_has_a_peak_row_that_agrees_with_validate(peak):
    m = metrics(peak=peak, peak_flag=peak <= 0.03)
    rows = summary_verdicts(m)
    (peak_row,) = [(name, ok) for name, ok in rows if "peak" in name]
    assert peak_row[1] is (peak <= 0.03)
    assert f"{100 * peak:.2f} %" in peak_row[0].replace("\u00a0", " ")
    # every badge of the summary passes exactly when validate's verdict does
    assert all(ok for _, ok in rows) is validate.passed(m)


def test_a_failed_peak_shows_a_fail_badge_in_the_summary_of_the_page():
    m = metrics(peak=0.0315, peak_flag=False)
    page = to_html(sections._summary(fake_run(m)))
    assert page.count('class="fail"') == 1 and page.count('class="ok"') == 1


class _Cells(HTMLParser):
    def __init__(self, page: str):
        super().__init__()
        self.rows: list[list[str]] = []
        self.inside = False
        self.feed(page)

    def handle_starttag(self, tag, attrs):
        if tag == "tr":
            self.rows.append([])
        elif tag == "td":
            self.rows[-1].append("")
            self.inside = True

    def handle_endtag(self, tag):
        self.inside = self.inside and tag != "td"

    def handle_data(self, data):
        if self.inside:
            self.rows[-1][-1] += data


@pytest.mark.parametrize(
    "albedo, flag",
    [(1.2, True), (0.9, True), (1.2, False), (0.9, False)],
    ids=["over-limit-flagged-passed", "within", "over-limit-failed", "within-flagged-failed"],
)
def test_each_physics_badge_agrees_with_its_value_and_limit(albedo, flag):
    m = metrics(albedo=albedo, albedo_flag=flag)
    row = physics_rows(m)["max_albedo"]
    expected = flag and albedo <= LIMITS["max_albedo"]
    assert row[-1].passed is expected
    # the page's row: its value, its limit and its badge
    page = to_html(sections._physics(fake_run(m), b"\x89PNG\r\n\x1a\n" + bytes(16)))
    (cells,) = [r for r in _Cells(page).rows if r and r[0] == "max_albedo"]
    assert cells[1].startswith(f"{albedo:.6f}") and cells[2] == f"<= {LIMITS['max_albedo']:g}"
    assert cells[3] == ("ok" if expected else "FAIL")
    (physics,) = [ok for name, ok in summary_verdicts(m) if name == "physics checks"]
    assert physics is expected


def test_a_negative_minimum_fails_whatever_its_flag():
    m = metrics()
    m["checks"]["min_value"]["value"] = -0.5
    assert physics_rows(m)["min_value"][-1].passed is False
    broken = copy.deepcopy(m)
    broken["checks"]["min_value"]["value"] = float("nan")
    assert physics_rows(broken)["min_value"][-1].passed is False

"""Regenerate analytic/data/conductors.json from spectral IOR files.

    python tools/make_conductor_presets.py IOR_DIR    # a folder of ior/*.spd files

Each preset is the spectral (eta, k) of the luxpop data (as distributed in
mitsuba-data ``ior/*.spd``: wavelength in nm, value) projected to linear sRGB: the
spectrum is integrated against the CIE 1931 colour-matching functions, here the
multi-lobe analytic fit of Wyman, Sloan & Shirley 2013 ("Simple Analytic
Approximations to the CIE XYZ Color Matching Functions", JCGT 2(2)), normalised by
the integral of y-bar, and converted XYZ -> linear sRGB (IEC 61966-2-1 matrix).  This
is our own conversion; Mitsuba's RGB values (the tests' reference data) are the independent
reference the tests compare against (tests/analytic/test_known_answers.py).
"""

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout
from neural_brdf.fileio import atomic_write  # noqa: E402

MATERIALS = ("Au", "Ag", "Cu", "Al")
LAMBDA = np.linspace(360.0, 830.0, 4701)  # nm, 0.1 nm steps
XYZ_TO_SRGB = np.array(
    [[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]]
)


def _lobe(lam, mu, s1, s2):
    s = np.where(lam < mu, s1, s2)
    return np.exp(-0.5 * ((lam - mu) / s) ** 2)


def cmf(lam: np.ndarray) -> np.ndarray:
    """CIE 1931 x-bar, y-bar, z-bar: Wyman et al. 2013, multi-lobe fit (their eq. 2)."""
    x = (
        1.056 * _lobe(lam, 599.8, 37.9, 31.0)
        + 0.362 * _lobe(lam, 442.0, 16.0, 26.7)
        - 0.065 * _lobe(lam, 501.1, 20.4, 26.2)
    )
    y = 0.821 * _lobe(lam, 568.8, 46.9, 40.5) + 0.286 * _lobe(lam, 530.9, 16.3, 31.1)
    z = 1.217 * _lobe(lam, 437.0, 11.8, 36.0) + 0.681 * _lobe(lam, 459.0, 26.0, 13.8)
    return np.stack([x, y, z], -1)


def spectrum_to_rgb(wl: np.ndarray, val: np.ndarray) -> np.ndarray:
    c = cmf(LAMBDA)
    xyz = (c * np.interp(LAMBDA, wl, val)[:, None]).sum(0) / c[:, 1].sum()
    return XYZ_TO_SRGB @ xyz


def read_spd(path: Path) -> tuple[np.ndarray, np.ndarray]:
    rows = [
        line.split()
        for line in path.read_text().splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]
    data = np.array(rows, dtype=np.float64)
    return data[:, 0], data[:, 1]


def main(src: str) -> None:
    out = {
        "_source": "luxpop spectral data (mitsuba-data ior/*.spd) projected to linear sRGB "
        "with CIE 1931 CMFs (Wyman et al. 2013 fit); "
        "regenerate with tools/make_conductor_presets.py"
    }
    for m in MATERIALS:
        entry = {}
        for part in ("eta", "k"):
            wl, val = read_spd(Path(src) / f"{m}.{part}.spd")
            entry[part] = [round(float(v), 6) for v in spectrum_to_rgb(wl, val)]
        out[m] = entry
    dest = Path(__file__).resolve().parents[1] / "analytic" / "data" / "conductors.json"
    atomic_write(dest, json.dumps(out, indent=1) + "\n")
    print(f"wrote {dest}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print("usage: python tools/make_conductor_presets.py IOR_DIR", file=sys.stderr)
        sys.exit(2)
    main(sys.argv[1])

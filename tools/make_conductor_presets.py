"""Regenerate analytic/data/conductors.json from spectral IOR files.

    python tools/make_conductor_presets.py ../shared/data/ior

Each preset is the spectral (eta, k) of the luxpop data (as distributed in
mitsuba-data ``ior/*.spd``: wavelength in nm, value), linearly interpolated at the
RGB wavelengths 650 / 550 / 450 nm.  This is a plain point-sampling of the spectrum,
deliberately independent of Mitsuba's CIE-weighted RGB conversion, which the tests
compare against (tests/test_known_answers.py states the tolerance).
"""

import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

WAVELENGTHS = (650.0, 550.0, 450.0)
MATERIALS = ("Au", "Ag", "Cu", "Al")


def read_spd(path: Path) -> tuple[np.ndarray, np.ndarray]:
    rows = [line.split() for line in path.read_text().splitlines()
            if line.strip() and not line.lstrip().startswith("#")]
    data = np.array(rows, dtype=np.float64)
    return data[:, 0], data[:, 1]


def main(src: str) -> None:
    out = {"_source": "luxpop spectral data (mitsuba-data ior/*.spd), linear interpolation "
                      "at 650/550/450 nm; regenerate with tools/make_conductor_presets.py"}
    for m in MATERIALS:
        entry = {}
        for part in ("eta", "k"):
            wl, val = read_spd(Path(src) / f"{m}.{part}.spd")
            entry[part] = [round(float(np.interp(w, wl, val)), 6) for w in WAVELENGTHS]
        out[m] = entry
    dest = Path(__file__).resolve().parents[1] / "analytic" / "data" / "conductors.json"
    fd, tmp = tempfile.mkstemp(dir=dest.parent)
    with os.fdopen(fd, "w") as fh:
        json.dump(out, fh, indent=1)
        fh.write("\n")
    os.replace(tmp, dest)
    print(f"wrote {dest}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/ior")

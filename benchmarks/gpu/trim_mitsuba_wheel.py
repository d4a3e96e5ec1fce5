"""Trim the mitsuba cp312 wheel to what the GPU run needs (RGB variants, the plugins a
surface scene uses) so that it fits the 64 MiB that travels; RECORD is rewritten.
    python benchmarks/gpu/trim_mitsuba_wheel.py IN.whl OUT.whl [--keep-llvm]"""

import base64
import hashlib
import re
import sys
import zipfile

src, dst = sys.argv[1], sys.argv[2]
keep_llvm = "--keep-llvm" in sys.argv
VARIANT = re.compile(r"mitsuba/(scalar|llvm|cuda)_[a-z_]+\.cpython-312-x86_64-linux-gnu\.so$")
KEEP_VARIANTS = {"scalar_rgb", "cuda_ad_rgb"} | ({"llvm_ad_rgb"} if keep_llvm else set())
DROP_PLUGINS = {
    "volpath",
    "volpathmis",
    "ellipsoids",
    "ellipsoidsmesh",
    "bsplinecurve",
    "linearcurve",
    "sdfgrid",
    "sunsky",
    "timed_sunsky",
    "hair",
    "ptracer",
    "measured_polarized",
    "principledthin",
}


def keep(name: str) -> bool:
    m = VARIANT.match(name)
    if m:
        return name.split("/")[1].split(".")[0] in KEEP_VARIANTS
    if name == "mitsuba/data/srgb.coeff" or name.startswith("mitsuba/data/sunsky/"):
        return False  # spectral upsampling table / sky datasets: unused by RGB surface scenes
    if name.startswith("mitsuba/plugins/"):
        return name.rsplit("/", 1)[1].removesuffix(".so") not in DROP_PLUGINS
    return True


zin = zipfile.ZipFile(src)
record_name = next(n for n in zin.namelist() if n.endswith(".dist-info/RECORD"))
rows, dropped = [], 0
with zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zout:
    for info in zin.infolist():
        if info.filename == record_name:
            continue
        if not keep(info.filename):
            dropped += info.file_size
            continue
        data = zin.read(info)
        zout.writestr(info, data, compress_type=zipfile.ZIP_DEFLATED, compresslevel=9)
        if not info.is_dir():
            h = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
            rows.append(f"{info.filename},sha256={h},{len(data)}")
    rows.append(f"{record_name},,")
    zout.writestr(record_name, "\n".join(rows) + "\n")
print(f"dropped {dropped / 2**20:.1f} MiB uncompressed")

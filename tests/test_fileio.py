"""neural_brdf.fileio: the one atomic-write helper every writer uses, and what it does
with a path that is a FIFO, a device, a symbolic link or a folder."""

import ast
import errno
import math
import os
import stat
import threading
from pathlib import Path

import pytest

from neural_brdf import fileio
from neural_brdf.fileio import atomic_path, atomic_write


@pytest.fixture
def umask():
    old = os.umask(0o022)
    yield lambda m: os.umask(m)
    os.umask(old)


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_new_file_gets_the_umask_permissions(tmp_path, umask, mask, mode):
    umask(mask)
    atomic_write(tmp_path / "f.json", "{}")
    assert os.stat(tmp_path / "f.json").st_mode & 0o777 == mode
    assert (tmp_path / "f.json").read_text() == "{}"


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "ckpt.pt"
    atomic_write(path, b"old")
    with pytest.raises(KeyboardInterrupt), atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(b"half a checkpoint")
        raise KeyboardInterrupt
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt"]


def test_missing_folders_only_on_request(tmp_path):
    path = tmp_path / "a" / "b" / "model.onnx"
    with pytest.raises(FileNotFoundError):
        atomic_write(path, b"1")  # a mistyped -o folder is an error
    assert not (tmp_path / "a").exists()
    atomic_write(path, b"1", parents=True)
    atomic_write(path, b"22")
    assert path.read_bytes() == b"22"


@pytest.mark.parametrize("depth", [1, 2], ids=["its folder", "a folder above"])
def test_a_file_where_a_folder_goes_is_named(tmp_path, depth):
    # (-o notes.txt/model.onnx said "File exists", naming neither the file nor why)
    (tmp_path / "notes.txt").write_text("mine")
    path = tmp_path / "notes.txt" / ("sub/" * (depth - 1)) / "model.onnx"
    with pytest.raises(NotADirectoryError) as e:
        atomic_write(path, b"1", parents=True)
    assert e.value.filename == str(path), e.value
    assert f"{tmp_path / 'notes.txt'} is a file, not a folder" in str(e.value), e.value
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_a_name_ending_with_a_separator_is_a_folders(tmp_path):
    """``out.h/`` names a folder: Path drops the separator, and the file ``out.h`` was
    written, or replaced, in its place."""
    kept = tmp_path / "out.h"
    kept.write_text("KEEP")
    for name in (kept, tmp_path / "new.h"):
        with pytest.raises(NotADirectoryError, match="folder"):
            atomic_write(str(name) + os.sep, "x")
    assert kept.read_text() == "KEEP" and not (tmp_path / "new.h").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.h"]


def test_temporary_of_names_the_file_a_killed_write_was_for(tmp_path):
    """What a process killed mid-write leaves is recognised by the writer's own rule
    (runfolder removes a run's: fileio.temporary_of); nothing else is."""
    target = tmp_path / "ckpt.pt"
    for _ in range(20):  # mkstemp's names are random: several of them
        with fileio.atomic_path(target) as tmp:
            assert fileio.temporary_of(Path(tmp).name) == "ckpt.pt", tmp
            Path(tmp).write_bytes(b"x")
    for name in ("ckpt.pt", ".ckpt.pt.tmp", ".ckpt.pt.bak.tmp", ".ckpt.pt.ABCDEFGH.tmp", "x.tmp"):
        assert fileio.temporary_of(name) is None, name


def test_no_other_module_writes_through_mkstemp():
    """Every atomic write of the package goes through fileio (one helper, not copies)."""
    package = Path(fileio.__file__).parent
    users = sorted(p.name for p in package.rglob("*.py") if "mkstemp" in p.read_text())
    assert users == ["fileio.py"]


# (file, the call's first line) of the writes that are not a user's file, each with why
NOT_A_USERS_FILE = {
    # the reference's ONNX bytes, into a TemporaryDirectory of its own
    ("viewer/page.py", "onnx_path.write_bytes(payload)"),
}


def _dotted(node: ast.expr) -> str:
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if isinstance(node, ast.Name):
        parts.append(node.id)
    return ".".join(reversed(parts))


def _whole_write_names(tree: ast.AST) -> set[str]:
    """Names a module writes through whole: bound by ``with atomic_path(...) as name``
    or assigned a buffer (``io.BytesIO()``, ``io.StringIO()``)."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.With):
            for item in node.items:
                call, name = item.context_expr, item.optional_vars
                if isinstance(call, ast.Call) and isinstance(name, ast.Name):
                    if _dotted(call.func).endswith("atomic_path"):
                        out.add(name.id)
        elif isinstance(node, ast.Assign) and isinstance(node.value, ast.Call):
            if _dotted(node.value.func).split(".")[-1] in ("BytesIO", "StringIO"):
                out |= {t.id for t in node.targets if isinstance(t, ast.Name)}
    return out


def direct_writes(source: str) -> list[str]:
    """The first line of each call in ``source`` that writes a file in place: ``open``,
    ``ZipFile`` or ``fdopen`` in a mode with w, x or +; ``write_text``, ``write_bytes``;
    shutil's copies and moves; ``savefig``, ``torch.save``, ``np.save`` and ``onnx.save``
    to anything but a buffer or a name ``atomic_path`` gave."""
    tree = ast.parse(source)
    whole = _whole_write_names(tree)
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        name = _dotted(node.func)
        head, last = name.split(".")[0], name.split(".")[-1]
        if last in ("open", "ZipFile", "fdopen"):
            mode = next((k.value for k in node.keywords if k.arg == "mode"), None)
            if mode is None and len(node.args) > 1:
                mode = node.args[1]
            bad = isinstance(mode, ast.Constant) and set(str(mode.value)) & set("wx+")
        elif last in ("write_text", "write_bytes"):
            bad = True
        elif head == "shutil" and last in ("copy", "copy2", "copyfile", "copytree", "move"):
            bad = True
        elif last == "savefig" or (last == "save" and head in ("torch", "np", "numpy", "onnx")):
            pos = 1 if head in ("torch", "onnx") else 0
            target = node.args[pos] if len(node.args) > pos else None
            bad = not (isinstance(target, ast.Name) and target.id in whole)
        else:
            bad = False
        if bad:
            found.append((ast.get_source_segment(source, node) or name).splitlines()[0])
    return found


def test_the_write_scan_finds_writes_in_place_and_passes_whole_ones():
    flagged = direct_writes(
        "open(os.path.join(a, b), 'w+')\n"
        "open(p, mode='wb')\n"
        "zipfile.ZipFile(p, 'w')\n"
        "Path(p).write_text(t)\n"
        "shutil.copyfile(a, b)\n"
        "fig.savefig(path, dpi=110)\n"
        "torch.save(\n    state,\n    path,\n)\n"
        "np.save(out, arr)\n"
    )
    assert len(flagged) == 8, flagged
    whole = (
        "open(p)\nopen(p, 'rb')\nopen(p, 'a', newline='')\n"
        "buf = io.BytesIO()\nfig.savefig(buf, format='png')\ntorch.save(state, buf)\n"
        "with atomic_path(path, suffix='.png') as tmp:\n    fig.savefig(tmp)\n"
    )
    assert direct_writes(whole) == []


def test_every_write_of_the_package_is_atomic():
    """No module but fileio writes a file in place (truncating it first: ``open(...,
    "w")``, ``write_text``, ``savefig(path)``, ``torch.save(obj, path)``, ...): each
    writes whole through fileio, so that an interrupted or failed write leaves the file
    as it was.  A log is appended to after fileio has written its head."""
    package = Path(fileio.__file__).parent
    found = set()
    for path in sorted(package.rglob("*.py")):
        rel = path.relative_to(package).as_posix()
        if rel != "fileio.py":
            found |= {(rel, line) for line in direct_writes(path.read_text())}
    assert found == NOT_A_USERS_FILE, sorted(found - NOT_A_USERS_FILE)


# ---------------------------------------------------------------- what the path already is
DEVICES = {"/dev/null": (1, 3), "/dev/full": (1, 7)}


@pytest.fixture
def devices():
    """Fails a test that turned /dev/null or /dev/full into a regular file, and puts the
    device back (as root), so that a regression does not break the machine."""
    yield
    for path, (major, minor) in DEVICES.items():
        if not stat.S_ISCHR(os.lstat(path).st_mode):
            if os.geteuid() == 0:
                os.unlink(path)
                os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(major, minor))
                os.chmod(path, 0o666)
            pytest.fail(f"{path} is no longer a character device")


def read_fifo_in_thread(path):
    """Start a reader of the FIFO ``path``; returns a function that joins it -> bytes."""
    got = []
    reader = threading.Thread(target=lambda: got.append(Path(path).read_bytes()), daemon=True)
    reader.start()

    def join():
        reader.join(timeout=60)
        assert got, "the FIFO's reader got nothing"
        return got[0]

    return join


def test_a_fifo_is_written_not_replaced(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    payload = b"0123456789" * 20000  # more than a pipe buffer: written in several parts
    join = read_fifo_in_thread(fifo)
    atomic_write(fifo, payload)
    assert join() == payload
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    join = read_fifo_in_thread(fifo)
    with atomic_path(fifo, suffix=".png") as name:  # a writer that wants a file name
        Path(name).write_bytes(b"through a name")
    assert join() == b"through a name"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipe"]


def test_a_symlink_is_followed_and_stays_a_link(tmp_path):
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "brdf.h"
    target.write_text("old")
    link = tmp_path / "link.h"
    link.symlink_to(target)
    atomic_write(link, "new")
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.h", "real"]
    assert sorted(p.name for p in target.parent.iterdir()) == ["brdf.h"]
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "real" / "new.json")
    atomic_write(dangling, "{}")
    assert dangling.is_symlink() and (tmp_path / "real" / "new.json").read_text() == "{}"


def test_dev_null_stays_a_device(devices):
    atomic_write("/dev/null", b"x" * 100)
    with atomic_path("/dev/null", suffix=".png") as name:
        Path(name).write_bytes(b"y")
    assert stat.S_ISCHR(os.lstat("/dev/null").st_mode)


def test_dev_full_is_enospc_naming_the_path(devices):
    with pytest.raises(OSError) as err:
        atomic_write("/dev/full", "x")
    assert err.value.errno == errno.ENOSPC and err.value.filename == "/dev/full"
    assert stat.S_ISCHR(os.lstat("/dev/full").st_mode)


def test_a_full_disk_names_the_file_and_leaves_nothing(tmp_path, monkeypatch):
    path = tmp_path / "ckpt.pt"
    atomic_write(path, b"old")

    def full(fd, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "write", full)
    with pytest.raises(OSError) as err:
        atomic_write(path, b"new")
    monkeypatch.undo()
    assert err.value.errno == errno.ENOSPC and err.value.filename == str(path)
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt"]


def test_a_folder_is_refused_and_a_replaced_file_keeps_its_mode(tmp_path):
    with pytest.raises(IsADirectoryError):
        atomic_write(tmp_path, "x")
    path = tmp_path / "private.json"
    path.write_text("{}")
    os.chmod(path, 0o600)
    atomic_write(path, "[]")
    assert path.read_text() == "[]" and os.stat(path).st_mode & 0o777 == 0o600


# ------------------------------------------------------------------ JSON reports
def test_json_text_writes_every_non_finite_number_one_way():
    """One rule for the reports (metrics.json, validate --json, a sweep's results): a
    NaN or an infinity, at any depth and of any float type, is the string Python writes."""
    import json

    import numpy as np

    from neural_brdf.fileio import json_text

    value = {
        "a": [float("nan"), {"b": np.float64("inf"), "c": (np.float32(1.5), -math.inf)}],
        "d": np.array([1.0, np.nan]),
        "e": Path("x/y"),
    }
    back = json.loads(json_text(value))
    assert back == {"a": ["nan", {"b": "inf", "c": [1.5, "-inf"]}], "d": [1.0, "nan"], "e": "x/y"}


def test_the_report_writers_share_the_json_rule(tmp_path):
    """validate.write_json and a sweep's trial file write nested non-finite numbers as
    strings (the sweep's writer raised on one inside a list before)."""
    import json

    from neural_brdf import validate
    from neural_brdf.tooling.sweep import trial

    report = {"checks": {"x": {"value": math.inf}}, "rows": [[math.nan]]}
    validate.write_json(report, tmp_path / "m.json")
    trial._write_json(tmp_path / "t.json", report)
    for name in ("m.json", "t.json"):
        assert json.loads((tmp_path / name).read_text()) == {
            "checks": {"x": {"value": "inf"}},
            "rows": [["nan"]],
        }


# ------------------------------------------------------------------ reading
@pytest.fixture
def no_hang():
    """A read that blocks (a FIFO opened for reading waits for a writer) fails the test
    after 20 s instead of hanging it: SIGALRM interrupts the open."""
    import signal

    def alarm(signum, frame):
        raise TimeoutError("blocked reading a FIFO")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(20)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_reading_refuses_a_fifo_and_a_device_without_blocking(tmp_path, no_hang):
    fifo = tmp_path / "x.yaml"
    os.mkfifo(fifo)  # never opened for writing: a reader that opens it would block
    zero = tmp_path / "zero.yaml"
    zero.symlink_to("/dev/zero")
    for path, kind in ((fifo, "a FIFO"), (zero, "a character device")):
        with pytest.raises(fileio.NotAFileError) as e:
            fileio.read_capped(path, 100)
        assert str(e.value) == f"{path}: is {kind}, not a file"
    (tmp_path / "f.txt").write_bytes(b"x" * 50)
    assert fileio.read_capped(tmp_path / "f.txt", 10) == b"x" * 11  # limit + 1 at most
    with pytest.raises(IsADirectoryError):
        fileio.open_for_reading(tmp_path)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_config_that_is_a_fifo_or_a_device_is_refused_by_name(tmp_path, no_hang):
    from neural_brdf import config
    from neural_brdf.errors import ConfigError

    fifo = tmp_path / "x.yaml"
    os.mkfifo(fifo)
    zero = tmp_path / "z.yaml"
    zero.symlink_to("/dev/urandom")  # st_size 0: the size check alone let it through
    for path, kind in ((fifo, "a FIFO"), (zero, "a character device")):
        with pytest.raises(ConfigError) as e:
            config.read_text(path)
        msg = str(e.value)
        assert msg.startswith(f"{path}: is {kind}, not a file") and "\n" not in msg, msg


def test_a_measured_file_given_as_a_config_is_named_as_measured_data(tmp_path, capsys):
    """train, bake, render --reference and view --compare said "more than a config may be"
    (or "not UTF-8") of a MERL or RGL file (validate --reference takes one)."""
    from cli_helpers import assert_one_line_error, cli
    from neural_brdf import config, limits
    from neural_brdf.errors import ConfigError

    merl_file = tmp_path / "gold.binary"
    merl_file.write_bytes(bytes(limits.MAX_CONFIG_BYTES + 10))  # larger than a config
    rgl_file = tmp_path / "gold.pbsdf"  # an RGL tensor file, known by its first bytes
    rgl_file.write_bytes(b"tensor_file\0\1\0" + bytes(100))
    model = tmp_path / "m.onnx"  # (refused before the model is read)
    for path, what in ((merl_file, "MERL .binary"), (rgl_file, "RGL .bsdf")):
        for command in (
            ["train", str(path), "--out", str(tmp_path / "run")],
            ["bake", str(path), "-o", str(tmp_path / "x.bsdf")],
            ["render", str(model), "--reference", str(path), "-o", str(tmp_path / "r.png")],
            ["view", str(model), "--compare", str(path), "-o", str(tmp_path / "v.html")],
        ):
            code, _, err = cli(capsys, *command)
            assert_one_line_error(code, err, f"{path}: measured data ({what}), not a config")
    big = tmp_path / "big.yaml"  # no measured file: still refused by its size
    big.write_bytes(b"#" * (limits.MAX_CONFIG_BYTES + 10))
    with pytest.raises(ConfigError, match="more than a config may be"):
        config.read_text(big)

"""neural_brdf.fileio: the one atomic-write helper every writer uses."""

import os
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


def test_no_other_module_writes_through_mkstemp():
    """Every atomic write of the package goes through fileio (one helper, not copies)."""
    package = Path(fileio.__file__).parent
    users = sorted(p.name for p in package.rglob("*.py") if "mkstemp" in p.read_text())
    assert users == ["fileio.py"]

"""Where numba keeps the compiled kernels when neither the package nor the home folder can hold them
(edi_live.kernel_cache). Folders are made unwritable by a plain file standing where the folder must be, which
stops root too; the temp directory is the test's own."""

from __future__ import annotations

import os
import stat
import sys
import tempfile
from pathlib import Path

import pytest

from edi_live import kernel_cache

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="numba's user cache folder is set up for Linux here")


@pytest.fixture
def temp_dir(tmp_path, monkeypatch) -> Path:
    folder = tmp_path / "tmp"
    folder.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    return folder


def _blocked(tmp_path: Path, name: str) -> Path:
    """A folder path that cannot be created: a plain file holds its place."""
    (tmp_path / name).write_text("a file, not a folder\n")
    return tmp_path / name


def _only_owner_writes(top: Path) -> None:
    """Folders 0755 and files 0644 whatever the umask: kernels only their owner could have written."""
    for path in [top, *top.rglob("*")]:
        path.chmod(0o755 if path.is_dir() else 0o644)


def _package(tmp_path: Path, writable: bool) -> Path:
    package = tmp_path / "site" / "edi_live"
    package.mkdir(parents=True)
    if not writable:
        (package / "__pycache__").write_text("a file, not a folder\n")
    return package


def test_nothing_changes_where_the_package_or_the_home_or_the_given_folder_can_be_written(tmp_path, temp_dir):
    blocked = _blocked(tmp_path, "blocked")
    cases = [
        ({"XDG_CACHE_HOME": str(blocked / "cache")}, _package(tmp_path / "a", writable=True)),
        ({"XDG_CACHE_HOME": str(tmp_path / "cache")}, _package(tmp_path / "b", writable=False)),
        ({"XDG_CACHE_HOME": str(blocked / "cache"), "NUMBA_CACHE_DIR": str(tmp_path / "mine")},
         _package(tmp_path / "c", writable=False)),
    ]
    for environ, package in cases:
        before = dict(environ)
        assert kernel_cache.choose(environ, package) == ""
        assert environ == before
    assert not any(temp_dir.iterdir())


def test_with_no_writable_folder_the_kernels_go_to_a_private_folder_of_this_user_and_the_notice_says_where(
        tmp_path, temp_dir):
    environ = {"XDG_CACHE_HOME": str(_blocked(tmp_path, "blocked") / "cache")}
    package = _package(tmp_path, writable=False)
    notice = kernel_cache.choose(environ, package)
    folder = Path(environ["NUMBA_CACHE_DIR"])
    assert folder == temp_dir / f"edi-live-numba-{os.getuid()}"
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert str(folder) in notice and str(package / "__pycache__") in notice and "NUMBA_CACHE_DIR" in notice
    again = {"XDG_CACHE_HOME": environ["XDG_CACHE_HOME"], "NUMBA_CACHE_DIR": str(_blocked(tmp_path, "x") / "y")}
    assert str(folder) in kernel_cache.choose(again, package)  # an unwritable NUMBA_CACHE_DIR: the same way out
    assert Path(again["NUMBA_CACHE_DIR"]) == folder


@pytest.mark.parametrize("spoiled", ["group-writable", "a link"])
def test_a_temp_folder_of_that_name_that_others_could_write_is_not_used(tmp_path, temp_dir, spoiled):
    """numba loads pickles from its cache: a folder another account made or can write to would run its code."""
    name = temp_dir / f"edi-live-numba-{os.getuid()}"
    if spoiled == "a link":
        (tmp_path / "elsewhere").mkdir()
        name.symlink_to(tmp_path / "elsewhere")
    else:
        name.mkdir()
        name.chmod(0o770)
    environ = {"XDG_CACHE_HOME": str(_blocked(tmp_path, "blocked") / "cache")}
    kernel_cache.choose(environ, _package(tmp_path, writable=False))
    folder = Path(environ["NUMBA_CACHE_DIR"])
    assert folder.parent == temp_dir and folder != name
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700 and not folder.is_symlink()


def test_kernels_in_a_given_folder_this_account_cannot_write_are_copied_to_its_own_folder(tmp_path, temp_dir,
                                                                                         monkeypatch):
    """A container image compiles its kernels into NUMBA_CACHE_DIR as one account; run with `--user`, another
    account can read that folder but not write it, and numba uses no folder it cannot write. The private folder
    starts from a copy, so the image's kernels still load. (Root can write anywhere: the check is told instead.)"""
    image_cache = tmp_path / "image-cache"
    (image_cache / "edi_abc").mkdir(parents=True)
    (image_cache / "edi_abc" / "k.py311.nbi").write_bytes(b"index")
    (image_cache / "edi_abc" / "k.py311.1.nbc").write_bytes(b"code")
    _only_owner_writes(image_cache)
    writable = kernel_cache._writable
    monkeypatch.setattr(kernel_cache, "_writable", lambda folder: folder != image_cache and writable(folder))
    environ = {"XDG_CACHE_HOME": str(_blocked(tmp_path, "blocked") / "cache"), "NUMBA_CACHE_DIR": str(image_cache)}
    notice = kernel_cache.choose(environ, _package(tmp_path, writable=False))
    folder = Path(environ["NUMBA_CACHE_DIR"])
    assert folder.parent == temp_dir
    assert (folder / "edi_abc" / "k.py311.nbi").read_bytes() == b"index"
    assert (folder / "edi_abc" / "k.py311.1.nbc").read_bytes() == b"code"
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert "copy" in notice and str(image_cache) in notice


def test_the_copied_kernels_take_no_folder_modes_from_the_given_folder(tmp_path, temp_dir, monkeypatch):
    """The private folder and all below it are this account's alone (0700), whatever the modes of the given folder:
    copied modes (copytree's) opened it to others while it was filled, and left its subfolders as open as those."""
    image_cache = tmp_path / "image-cache"
    (image_cache / "edi_abc").mkdir(parents=True)
    (image_cache / "edi_abc" / "k.py311.nbi").write_bytes(b"index")
    _only_owner_writes(image_cache)
    writable = kernel_cache._writable
    monkeypatch.setattr(kernel_cache, "_writable", lambda folder: folder != image_cache and writable(folder))
    environ = {"XDG_CACHE_HOME": str(_blocked(tmp_path, "blocked") / "cache"), "NUMBA_CACHE_DIR": str(image_cache)}
    kernel_cache.choose(environ, _package(tmp_path, writable=False))
    folder = Path(environ["NUMBA_CACHE_DIR"])
    assert (folder / "edi_abc" / "k.py311.nbi").read_bytes() == b"index"
    for sub in [folder, *[p for p in folder.rglob("*") if p.is_dir()]]:
        assert not stat.S_IMODE(sub.stat().st_mode) & 0o077, (sub, oct(sub.stat().st_mode))


def test_only_kernels_no_other_account_could_have_written_are_copied(tmp_path, temp_dir, monkeypatch):
    """numba never loads from a cache folder it cannot write, so before the copy nothing in the given folder ran;
    copied into the private folder it would. A file or folder another account owns or can write is left out."""
    image_cache = tmp_path / "image-cache"
    for sub in ("kept", "open"):
        (image_cache / sub).mkdir(parents=True)
        (image_cache / sub / "a.nbi").write_bytes(b"index")
    (image_cache / "kept" / "b.nbi").write_bytes(b"index")
    _only_owner_writes(image_cache)
    (image_cache / "open").chmod(0o777)
    (image_cache / "kept" / "b.nbi").chmod(0o666)
    if os.geteuid() == 0:  # only root can give a file away
        (image_cache / "kept" / "c.nbi").write_bytes(b"index")
        (image_cache / "kept" / "c.nbi").chmod(0o644)
        os.chown(image_cache / "kept" / "c.nbi", 54321, 54321)
    writable = kernel_cache._writable
    monkeypatch.setattr(kernel_cache, "_writable", lambda folder: folder != image_cache and writable(folder))
    environ = {"XDG_CACHE_HOME": str(_blocked(tmp_path, "blocked") / "cache"), "NUMBA_CACHE_DIR": str(image_cache)}
    kernel_cache.choose(environ, _package(tmp_path, writable=False))
    folder = Path(environ["NUMBA_CACHE_DIR"])
    copied = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
    assert copied == ["kept/a.nbi"]
    # with nothing it may copy, the notice does not claim a copy (the folders alone are no kernels)
    (image_cache / "kept" / "a.nbi").chmod(0o666)
    for made in sorted(folder.rglob("*"), reverse=True):
        made.unlink() if made.is_file() else made.rmdir()
    environ["NUMBA_CACHE_DIR"] = str(image_cache)
    assert "copy" not in kernel_cache.choose(environ, _package(tmp_path / "again", writable=False))


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="giving files to another account needs root")
def test_a_container_images_kernels_owned_by_its_own_account_are_copied_for_a_user_run(tmp_path, temp_dir,
                                                                                       monkeypatch):
    """docker/Dockerfile compiles the kernels as root, then gives the cache to its account `edi` so that `edi` can
    write it; run with `--user` another uid reads them. The owner of the folder NUMBA_CACHE_DIR names is trusted
    (whoever set the environment chose it); another owner inside it is not."""
    image_cache = tmp_path / "image-cache"
    (image_cache / "edi_abc").mkdir(parents=True)
    (image_cache / "edi_abc" / "k.py311.nbi").write_bytes(b"index")
    (image_cache / "edi_abc" / "other.nbi").write_bytes(b"index")
    _only_owner_writes(image_cache)
    for path in [image_cache, *image_cache.rglob("*")]:
        os.chown(path, 1000, 1000)
    os.chown(image_cache / "edi_abc" / "other.nbi", 54321, 54321)
    writable = kernel_cache._writable
    monkeypatch.setattr(kernel_cache, "_writable", lambda folder: folder != image_cache and writable(folder))
    environ = {"XDG_CACHE_HOME": str(_blocked(tmp_path, "blocked") / "cache"), "NUMBA_CACHE_DIR": str(image_cache)}
    notice = kernel_cache.choose(environ, _package(tmp_path, writable=False))
    folder = Path(environ["NUMBA_CACHE_DIR"])
    copied = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
    assert copied == ["edi_abc/k.py311.nbi"] and "copy" in notice


def test_the_user_cache_folder_is_the_one_numba_picks(tmp_path, monkeypatch):
    """The check must test the folder numba will use, or numba still finds none writable and raises at import."""
    from numba.misc.appdirs import AppDirs

    for value in ("", str(tmp_path / "xdg")):  # an empty XDG_CACHE_HOME is taken as it is by numba (the cwd)
        monkeypatch.setenv("XDG_CACHE_HOME", value)
        numba_choice = Path(AppDirs(appname="numba", appauthor=False).user_cache_dir)
        assert kernel_cache._user_cache(dict(os.environ)) == numba_choice


def test_a_copy_that_fails_midway_leaves_no_truncated_kernel_under_its_name(tmp_path, temp_dir, monkeypatch):
    """A full temp disk: numba would fail on the half file at every start (the private folder is kept)."""
    import errno

    image_cache = tmp_path / "image-cache"
    (image_cache / "edi_abc").mkdir(parents=True)
    for name in ("k.py311.nbi", "k.py311.1.nbc"):
        (image_cache / "edi_abc" / name).write_bytes(b"0123456789")
    _only_owner_writes(image_cache)
    copied = []

    def disk_full_at_the_second(source, dest):
        if copied:
            Path(dest).write_bytes(Path(source).read_bytes()[:4])
            raise OSError(errno.ENOSPC, "No space left on device")
        Path(dest).write_bytes(Path(source).read_bytes())
        copied.append(dest)

    monkeypatch.setattr(kernel_cache.shutil, "copyfile", disk_full_at_the_second)
    writable = kernel_cache._writable
    monkeypatch.setattr(kernel_cache, "_writable", lambda folder: folder != image_cache and writable(folder))
    environ = {"XDG_CACHE_HOME": str(_blocked(tmp_path, "blocked") / "cache"), "NUMBA_CACHE_DIR": str(image_cache)}
    kernel_cache.choose(environ, _package(tmp_path, writable=False))
    left = {p.name: p.read_bytes() for p in Path(environ["NUMBA_CACHE_DIR"]).rglob("*") if p.is_file()}
    assert len(copied) == 1 and all(data == b"0123456789" for data in left.values()), left
    assert set(left) <= {"k.py311.nbi", "k.py311.1.nbc"}, left

"""Where numba keeps the compiled kernels (its on-disk cache), chosen when edi_live is first imported.

A kernel declared with `cache=True` looks for a writable folder as it is defined: NUMBA_CACHE_DIR, then the
module's own `__pycache__`, then `~/.cache/numba`. Where none can be written (a package installed read-only, used
by an account without a writable home: a service account, a container run with `--user`), numba raises at import
and nothing of edi_live can be used. In that one case this module points NUMBA_CACHE_DIR at a private folder of
this user in the temp directory (made fresh for the process if that one cannot be trusted), and `notice()` says so
for the node to log. Everywhere else it changes nothing. Standard library only: importing edi_live loads no numba.
"""

from __future__ import annotations

import atexit
import os
import shutil
import stat
import sys
import tempfile
from collections.abc import Mapping, MutableMapping
from pathlib import Path

_PACKAGE_DIR = Path(__file__).resolve().parent


def _writable(folder: Path) -> bool:
    """Whether numba could keep its cache in `folder` (the test numba makes: create it, write a file in it)."""
    try:
        os.makedirs(folder, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def _user_cache(environ: Mapping[str, str]) -> Path:
    """numba's own fall-back folder (its appdirs rule on Linux and the other Unixes)."""
    if sys.platform == "darwin":
        return Path(os.path.expanduser("~/Library/Caches")) / "numba"
    if sys.platform == "win32":
        return Path(environ.get("LOCALAPPDATA", os.path.expanduser("~"))) / "numba" / "Cache"
    # as numba reads it: an empty XDG_CACHE_HOME is kept (a folder "numba" in the working directory)
    return Path(environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache"))) / "numba"


def _private_temp_folder() -> Path:
    """This user's folder in the temp directory, reused across runs only if it is this user's alone (numba loads
    pickles from it: a folder someone else made or can write to would run their code); else a fresh one."""
    uid = os.getuid() if hasattr(os, "getuid") else None
    if uid is not None:
        folder = Path(tempfile.gettempdir()) / f"edi-live-numba-{uid}"
        try:
            os.makedirs(folder, mode=0o700, exist_ok=True)
            st = os.lstat(folder)
            if stat.S_ISDIR(st.st_mode) and st.st_uid == uid and not st.st_mode & 0o022 and _writable(folder):
                return folder
        except OSError:
            pass
    fresh = Path(tempfile.mkdtemp(prefix="edi-live-numba-"))
    atexit.register(shutil.rmtree, fresh, ignore_errors=True)
    return fresh


def choose(environ: MutableMapping[str, str] = os.environ, package_dir: Path = _PACKAGE_DIR) -> str:
    """Set NUMBA_CACHE_DIR in `environ` when numba would find no writable cache folder for `package_dir`'s
    kernels; returns the notice for the person at the terminal ("" when nothing was changed)."""
    given = environ.get("NUMBA_CACHE_DIR", "")
    candidates = ([Path(given)] if given else []) + [package_dir / "__pycache__", _user_cache(environ)]
    if any(_writable(folder) for folder in candidates):  # in numba's order
        return ""
    try:
        folder = _private_temp_folder()
    except OSError as exc:  # no usable temp directory either: numba will say what it cannot do
        return f"numba kernel cache: no folder can be written ({exc}); set NUMBA_CACHE_DIR to one"
    environ["NUMBA_CACHE_DIR"] = str(folder)
    seeded = given and _seed(folder, Path(given))
    tried = ", ".join(f"NUMBA_CACHE_DIR={c}" if given and k == 0 else str(c) for k, c in enumerate(candidates))
    return (f"numba kernel cache: none of {tried} can be written, so compiled kernels go to {folder}"
            f"{' (started from a copy of the first)' if seeded else ''}, which the system may clear (the next start "
            f"then compiles again); set NUMBA_CACHE_DIR to a lasting folder this user can write")


def _seed(folder: Path, given: Path) -> bool:
    """Copy the kernels compiled into the NUMBA_CACHE_DIR this account cannot write (a container image's, run with
    `--user`) into the empty private folder, so they load instead of compiling again; numba only uses a cache folder
    it can write to. Returns whether any kernel file was copied."""
    copied = 0
    try:
        if not given.is_dir() or any(folder.iterdir()):
            return False
        # contents only, never modes (copytree copies them): a folder open to others, even for a moment, would let
        # them drop a pickle or keep a handle to drop one later
        owners = _trusted_owners(os.stat(given))
        for root, subfolders, files in os.walk(given):
            if not _only_trusted_write(os.stat(root), owners):
                subfolders.clear()
                continue
            target = folder / Path(root).relative_to(given)
            target.mkdir(mode=0o700, exist_ok=True)
            for name in files:
                st = os.lstat(Path(root) / name)
                if stat.S_ISREG(st.st_mode) and _only_trusted_write(st, owners):
                    _copy_whole(Path(root) / name, target / name)
                    copied += 1
    except OSError:
        return False
    return copied > 0


def _copy_whole(source: Path, dest: Path) -> None:
    """Copy under a temporary name, then rename: numba fails on a truncated kernel file (a full disk, or another
    process starting at the same moment reading it half-copied), and would find it again at every start."""
    part = dest.with_name(f".{dest.name}.{os.getpid()}.part")
    try:
        shutil.copyfile(source, part)
        os.replace(part, dest)
    except OSError:
        part.unlink(missing_ok=True)
        raise


def _trusted_owners(given: os.stat_result) -> tuple[int, ...]:
    """Who may have written the kernels copied: root, this account, and the owner of the folder NUMBA_CACHE_DIR names.
    That folder was chosen by whoever set up this process's environment, as PYTHONPATH is (a container image
    compiles its kernels into it as its own account, e.g. `edi` in docker/Dockerfile, and a `--user` run reads them);
    an account that merely owns a file inside it, or anyone who can write there, is not trusted."""
    if not hasattr(os, "getuid"):
        return ()
    return (0, os.getuid(), given.st_uid)


def _only_trusted_write(st: os.stat_result, owners: tuple[int, ...]) -> bool:
    """Whether only a trusted account can have written it: numba would load what another account put there
    (numba itself never loads from a folder it cannot write, so nothing of another account's ran before)."""
    if not hasattr(os, "getuid"):
        return True
    return st.st_uid in owners and not st.st_mode & 0o022


def notice() -> str:
    """What `choose` did when edi_live was imported, for the node to log ("" when numba's own choice stood)."""
    return _notice


def _apply() -> str:
    found = choose()
    if found and "numba.core.config" in sys.modules:  # numba was imported first and has read NUMBA_CACHE_DIR
        sys.modules["numba.core.config"].reload_config()
    return found


_notice = _apply()

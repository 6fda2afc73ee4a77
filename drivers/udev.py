"""The Linux udev rule that lets the logged-in user (and the plugdev group) open iniVation DAVIS cameras, and a
tiny CLI: `python -m drivers.udev` prints the rule, `sudo python -m drivers.udev --install` installs it.
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

from edi_live.console import print_lines
from edi_live.errors import OutputError

RULES_FILE = Path(__file__).resolve().parent / "99-edi-live-davis.rules"
RULE_TEXT = ('SUBSYSTEM=="usb", ATTR{idVendor}=="152a", ATTR{idProduct}=="84[0-1]?", MODE="0660", '
             'GROUP="plugdev", TAG+="uaccess"')
INSTALL_DIR = Path("/etc/udev/rules.d")


def install_command() -> str:
    """The command that installs the rule, with this Python: in a virtual environment `sudo python` would run the
    system's Python, which has no edi-live (No module named 'drivers')."""
    return f"sudo {shlex.quote(sys.executable)} -m drivers.udev --install"


def install(dest_dir: Path = INSTALL_DIR, *, reload: bool = True) -> Path:
    """Copy the rules file into `dest_dir` and (if `reload`) ask udev to reload (needs root for /etc)."""
    dest = Path(dest_dir) / RULES_FILE.name
    shutil.copyfile(RULES_FILE, dest)
    commands = [["udevadm", "control", "--reload-rules"], ["udevadm", "trigger"]] if reload else []
    for cmd in commands:
        try:
            subprocess.run(cmd, check=False, timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            pass  # no udevadm (containers): the file is in place, replugging applies it on the host
    return dest


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drivers.udev", description=__doc__)
    ap.add_argument("--install", action="store_true", help=f"copy the rule to {INSTALL_DIR} and reload udev")
    args = ap.parse_args(argv)
    if not args.install:
        try:
            print_lines(RULES_FILE.read_text().splitlines())  # ('| sudo tee FILE' that fails: no traceback)
        except OutputError as exc:  # ('> FILE' on a full disk)
            print(f"{ap.prog}: error: {exc}", file=sys.stderr)
            return 1
        return 0
    try:
        print(f"installed {install()}; unplug and replug the camera")
    except PermissionError:
        print(f"permission denied writing {INSTALL_DIR}: run {install_command()}", file=sys.stderr)
        return 1
    except OSError as exc:  # no such folder (not Linux, or a container without udev), a read-only /etc, ...
        print(f"cannot write the rule to {INSTALL_DIR}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

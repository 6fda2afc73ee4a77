"""How a user is told to install the udev rule: with the Python that has edi-live. A venv's edi-live is not on
root's path, so `sudo python -m drivers.udev --install` ran the system's Python: No module named 'drivers'."""

from __future__ import annotations

import shlex
import sys

from drivers import udev
from drivers.davis import transport


def _command_in(text: str) -> list[str]:
    start = text.index("sudo ")
    return shlex.split(text[start:].split(")")[0].split(",")[0])


def test_a_refused_install_names_the_command_with_this_python(monkeypatch, capsys):
    def refused(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(udev, "install", refused)
    assert udev.main(["--install"]) == 1
    said = capsys.readouterr()
    assert _command_in(said.err) == ["sudo", sys.executable, "-m", "drivers.udev", "--install"]


def test_the_permission_error_names_the_command_with_this_python_and_the_installed_rules_file():
    msg = transport.permission_message("DAVIS240 at usb 1:7")
    assert _command_in(msg) == ["sudo", sys.executable, "-m", "drivers.udev", "--install"]
    assert str(udev.RULES_FILE) in msg and udev.RULES_FILE.is_absolute()


def test_a_missing_rules_folder_is_one_line_not_a_traceback(monkeypatch, capsys):
    """No /etc/udev/rules.d (macOS, a minimal container): the copy raised FileNotFoundError out of main."""
    def missing(*args, **kwargs):
        raise FileNotFoundError(2, "No such file or directory", str(udev.INSTALL_DIR / udev.RULES_FILE.name))

    monkeypatch.setattr(udev, "install", missing)
    assert udev.main(["--install"]) == 1
    said = capsys.readouterr().err.strip()
    assert len(said.splitlines()) == 1 and str(udev.INSTALL_DIR) in said and "No such file or directory" in said

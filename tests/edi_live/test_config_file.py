"""Reading a --config TOML file (edi_live.config_file via edi_live.config.read_toml): what a broken, binary, huge or
missing file gives (one ConfigError naming the file), and where the paths in it point."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from edi_live import config_file
from edi_live.config import read_toml
from edi_live.errors import ConfigError


@pytest.mark.parametrize("text,fragment", [
    ("every = [", "not valid TOML"),
    ("[edi]\nevery = 3\n", "keys go at the top level"),
    ("evry = 3\n", "unknown key(s) evry"),
])
def test_bad_toml_files_are_config_errors_naming_the_file(tmp_path: Path, text, fragment):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        read_toml(path)
    assert fragment in str(info.value) and str(path) in str(info.value)


def test_a_config_file_that_starts_with_a_byte_order_mark_is_read(tmp_path: Path):
    # editors on Windows (Notepad) save UTF-8 with a BOM: "not valid TOML: Invalid statement (at line 1, column 1)"
    # pointed at a line that looks right, since the mark is invisible
    path = tmp_path / "edi.toml"
    path.write_bytes("every = 500\n".encode("utf-8-sig"))
    assert read_toml(path) == {"every": 500}


@pytest.mark.parametrize("key", ["calibrate-dark", "list-devices", "version"])
def test_a_one_shot_action_in_a_config_file_is_named_as_a_flag_only(tmp_path: Path, key):
    # "unknown key(s) calibrate_dark": a key the user did not write (the underscore) and a flag that exists, which
    # only cannot be in a file
    path = tmp_path / "edi.toml"
    path.write_text(f"{key} = 3\n")
    with pytest.raises(ConfigError) as info:
        read_toml(path)
    assert f"{key} " in str(info.value) and f"--{key}" in str(info.value) and "unknown" not in str(info.value)


def test_an_unknown_key_is_named_as_written(tmp_path: Path):
    path = tmp_path / "edi.toml"
    path.write_text("stats-intervall-s = 3\n")
    with pytest.raises(ConfigError, match="unknown key.s. stats-intervall-s$"):
        read_toml(path)


def test_a_binary_config_file_is_a_usage_error(tmp_path: Path):
    """Issue 15.7: a binary --config gave "internal error ... report it" (exit 1)."""
    path = tmp_path / "photo.toml"
    path.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ConfigError, match="not a TOML text file") as info:
        read_toml(path)
    assert info.value.exit_code == 2 and str(path) in str(info.value)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.one_of(st.binary(max_size=200),
                 st.lists(st.sampled_from(["every = 3\n", "c = 0.2\n", "[t]\n", "a = [\n", "x = \"\\u00\"\n",
                                           "replay = 'r'\n", "\x00", "\xff", "= 1\n", "loop = true\n"]),
                          max_size=6).map(lambda parts: "".join(parts).encode("utf-8", "surrogatepass"))))
def test_fuzzed_toml_files_give_a_mapping_or_a_config_error(tmp_path: Path, data):
    path = tmp_path / "fuzz.toml"
    path.write_bytes(data)
    try:
        options = read_toml(path)
    except ConfigError as exc:
        assert str(path) in str(exc)
        return
    assert isinstance(options, dict)


def test_missing_toml_file(tmp_path: Path):
    with pytest.raises(ConfigError, match="not found"):
        read_toml(tmp_path / "nope.toml")


def test_a_huge_config_file_is_refused_without_reading_it_all(tmp_path: Path):
    # --config /dev/zero ended in "internal error: MemoryError" (or a hang): the file was read whole
    from edi_live.config_file import MAX_CONFIG_BYTES

    big = tmp_path / "big.toml"
    with big.open("wb") as fh:
        fh.truncate(MAX_CONFIG_BYTES + 1)
    with pytest.raises(ConfigError, match="larger than 1 MiB"):
        read_toml(big)


def test_every_file_option_in_a_config_file_is_relative_to_the_file(tmp_path: Path, monkeypatch):
    """docs/node.md: "Relative paths in the file are relative to the file". The options that name a file are those
    whose flag takes a FILE; --calibration and --save-calibration were read against the working directory, so a
    config run from elsewhere loaded or wrote the calibration in the wrong place."""
    from edi_live.cli_parser import build_parser

    file_options = sorted(config_file.norm_key(action.option_strings[0]) for action in build_parser()._actions
                          if str(action.metavar or "").startswith("FILE") and action.dest != "config")
    assert {"replay", "calibration", "save_calibration", "out"} <= set(file_options)
    folder = tmp_path / "configs"
    folder.mkdir()
    path = folder / "edi.toml"
    path.write_text("".join(f'{key} = "{key}.file"\n' for key in file_options))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    options = read_toml(path)
    wrong = {key: value for key, value in options.items() if Path(value) != folder / f"{key}.file"}
    assert not wrong, wrong


def test_a_home_relative_path_in_a_config_file_is_in_the_home_folder(tmp_path: Path, monkeypatch):
    """A shell expands ~ in a flag; nothing did in a config file, so `calibration = "~/.config/edi-live/..."` (the
    folder a camera's calibration is kept in) was read as a folder named ~ beside the file."""
    home = tmp_path / "home"
    monkeypatch.setenv("HOME", str(home))
    path = tmp_path / "configs" / "edi.toml"
    path.parent.mkdir()
    path.write_text('calibration = "~/cal.json"\nreplay = "rec.aedat4"\n')
    options = read_toml(path)
    assert Path(options["calibration"]) == home / "cal.json"
    assert Path(options["replay"]) == path.parent / "rec.aedat4"


@pytest.mark.parametrize("key", ["dv-input", "publish"])
def test_an_endpoint_list_of_the_wrong_type_names_its_own_key(tmp_path: Path, key):
    """`dv-input = 5` in a config file was refused as "publish must be a list of endpoints (got 5)": the user was
    sent to fix a key the file did not have."""
    from edi_live.config import NodeConfig

    path = tmp_path / "edi.toml"
    path.write_text(f"{key} = 5\n")
    with pytest.raises(ConfigError) as info:
        NodeConfig.from_toml(path)
    assert str(info.value).startswith(f"{key}: ") and "list of endpoints" in str(info.value)
    assert "(got 5)" in str(info.value) and info.value.exit_code == 2


def test_one_option_spelled_twice_in_a_config_file_is_refused(tmp_path: Path):
    """`c-on = 0.2` and `c_on = 0.3` in one file (TOML sees two keys, edi-live one option) ran with 0.3 and no
    word: one of the two values the user wrote was silently dropped."""
    path = tmp_path / "edi.toml"
    path.write_text('c-on = 0.2\nc-off = 0.2\nc_on = 0.3\n')
    with pytest.raises(ConfigError) as info:
        read_toml(path)
    message = str(info.value)
    assert str(path) in message and "c-on" in message and "c_on" in message and info.value.exit_code == 2


_PATH_OPTIONS = ["replay", "out", "record", "calibration", "save_calibration", "curve_secret_key", "emulate_from"]


def _with_empty(key: str) -> dict:
    base = ({"device": "davis240", "usb_backend": "drivers.emulator:backend"} if key == "emulate_from"
            else {} if key == "replay" else {"replay": "rec.aedat4"})
    return {**base, key: ""}


@pytest.mark.parametrize("key", _PATH_OPTIONS)
def test_an_empty_file_path_is_a_usage_error_naming_its_option(tmp_path: Path, key):
    """`--save-calibration "$CAL"` with CAL unset ran the whole replay and then failed with "the main thread failed:
    ValueError: PosixPath('.') has an empty name", the calibration lost; an empty --out or --replay was read as the
    current folder (".: cannot create the recording (Is a directory)", exit 1). In a config file `out = ""` named
    the file's own folder."""
    from edi_live.config import NodeConfig

    flag = key.replace("_", "-")
    with pytest.raises(ConfigError) as info:
        NodeConfig.from_options(_with_empty(key))
    assert str(info.value).startswith(f"{flag}: ") and "(got '')" in str(info.value) and info.value.exit_code == 2
    path = tmp_path / "edi.toml"
    path.write_text("".join(f'{k.replace("_", "-")} = "{v}"\n' for k, v in _with_empty(key).items()))
    with pytest.raises(ConfigError) as info:
        NodeConfig.from_toml(path)
    assert str(info.value).startswith(f"{flag}: ") and "(got '')" in str(info.value)


@pytest.mark.parametrize("key", _PATH_OPTIONS)
def test_a_path_with_a_nul_character_is_a_usage_error_naming_its_option(tmp_path: Path, key):
    """TOML can hold "\\u0000", which no file name can: `out = "a\\u0000b"` ended in "internal error: ValueError:
    embedded null byte" (exit 1, "report it"), and `calibration` named a file without the NUL."""
    from edi_live.config import NodeConfig

    flag = key.replace("_", "-")
    options = {**_with_empty(key), key: "a\x00b"}
    path = tmp_path / "edi.toml"
    path.write_text("".join(f'{k.replace("_", "-")} = "{v}"\n' for k, v in options.items()).replace("\x00", "\\u0000"))
    with pytest.raises(ConfigError) as info:
        NodeConfig.from_toml(path)
    assert str(info.value).startswith(f"{flag}: ") and "NUL" in str(info.value) and info.value.exit_code == 2


def test_an_ipc_endpoint_with_a_nul_character_is_a_usage_error(tmp_path: Path):
    """`publish = ["ipc://edi.sock\\u0000y"]` ended in "the main thread failed: ValueError: embedded null byte"."""
    from edi_live.config import NodeConfig

    path = tmp_path / "edi.toml"
    path.write_text('replay = "rec.aedat4"\npublish = ["ipc://edi.sock\\u0000y"]\n')
    with pytest.raises(ConfigError) as info:
        NodeConfig.from_toml(path)
    assert "publish endpoint" in str(info.value) and "NUL" in str(info.value) and info.value.exit_code == 2

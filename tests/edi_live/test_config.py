"""NodeConfig: validation with "(got ...)" messages, the flags' keys, precedence flags > file > defaults (reading
the TOML file itself: test_config_file.py)."""

from __future__ import annotations

import dataclasses
import os
import threading
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edi_live import config_file
from edi_live.config import DEFAULT_ENDPOINT, OPTION_KEYS, NodeConfig, merge_options, read_toml
from edi_live.errors import ConfigError
from tests.helpers.pipes import written_pipe


def test_defaults_are_safe():
    cfg = NodeConfig.from_options({"replay": "x.aedat4"})
    assert cfg.publisher.endpoints == (DEFAULT_ENDPOINT,)  # loopback by default
    assert cfg.source.speed == 1.0 and cfg.edi.mode == "causal" and cfg.edi.every >= 1
    assert cfg.ring_policy == "wait"  # replay is lossless
    assert NodeConfig.from_options({"device": "auto"}).ring_policy == "drop_oldest"  # live never blocks USB
    emulated = NodeConfig.from_options({"device": "davis240", "usb_backend": "drivers.emulator:backend",
                                        "emulate_from": "x.aedat4"})
    assert emulated.ring_policy == "wait"


@pytest.mark.parametrize("options,fragment", [
    ({"replay": "x", "every": 0}, "every must be an integer in [1, 10^12]"),
    # issue 15.7: accepted silently before
    ({"replay": "x", "every": 10**23}, "every must be an integer in [1, 10^12] (events per latent frame) (got 1000"),
    ({"replay": "x", "publish": ["tcp://127.0.0.1:5555"], "no_publish": True}, "contradict each other"),
    ({"replay": "x", "ring_events": 10**11}, "of memory is available; choose at most"),
    ({"replay": "x", "ring_frames": 10**9}, "ring-frames must be an integer in [1, 10^6]"),
    ({"replay": "x", "reestimate_every": -1}, "reestimate-every must be an integer in [0, 10^9]"),
    # issue 15.5: libzmq wraps an out-of-range port (99999 bound 34463)
    ({"replay": "x", "publish": ["tcp://127.0.0.1:99999"]}, "port in 1-65535, or * for any free port"),
    ({"replay": "x", "publish": ["tcp://127.0.0.1:0"]}, "port in 1-65535"),
    ({"replay": "x", "publish": ["tcp://127.0.0.1"]}, "HOST:PORT"),
    ({"replay": "x", "publish": ["tcp://:5555"]}, "HOST:PORT"),
    ({"replay": "x", "publish": ["tcp://[]:5555"]}, "HOST:PORT"),  # empty IPv6 brackets: no host either
    ({"replay": "x", "publish": ["tcp://127.0.0.1:55a"]}, "port in 1-65535"),
    ({"replay": "x", "c": 10**400}, "c: int too large"),
    ({"replay": "x", "speed": -1}, "speed must be >= 0"),
    ({"replay": "x", "c": 0}, "(got 0"),
    ({"replay": "x", "c_on": 0.2}, "c-on and c-off go together"),
    ({"replay": "x", "c": 0.2, "c_on": 0.2, "c_off": 0.2}, "either c or c-on/c-off"),
    ({"replay": "x", "mode": "fast"}, "(got 'fast')"),
    ({"replay": "x", "max_fps": 0}, "max-fps must be a positive number"),
    ({"replay": "x", "device": "davis240"}, "choose one input"),
    ({"device": "davis999"}, "(got 'davis999')"),
    ({"device": "auto", "usb_backend": "nocolon"}, "MODULE:CALLABLE"),
    ({"device": "auto", "emulate_from": "x"}, "needs --usb-backend"),
    ({"replay": "x", "publish": ["5555"]}, "(got '5555')"),
    ({"replay": "x", "out": "a.aedat4", "record": "a.aedat4"}, "different files"),
    # checked with the other values: the node used to warn "serving DV on garbage: anyone ... can connect" first
    ({"replay": "x", "dv_output": "garbage"}, "--dv-output must look like tcp://HOST:PORT"),
    # a TOML value of the wrong type: our message naming the key, not Python's TypeError text
    ({"replay": 5}, "replay: expected a file path (got 5)"),
    ({"replay": "x", "out": True}, "out: expected a file path (got True)"),
    ({"device": "auto", "usb_backend": 5}, "usb-backend must look like MODULE:CALLABLE (got 5)"),
    ({"replay": "x", "dv_output_events": "tcp://0.0.0.0:99999"}, "--dv-output-events must look like tcp://HOST:PORT"),
    # accepted, and no subscriber outside the node's own process could ever reach it
    ({"replay": "x", "publish": ["inproc://frames"]}, "publish endpoint 'inproc://frames' is reachable only from "
                                                      "inside the edi-live process"),
    ({"replay": "x", "ring_events": 10}, "ring-events"),
    ({"replay": "x", "duration": -2}, "duration must be a positive number (got -2"),
    # accepted, then the run failed: "the main thread failed: OverflowError: cannot convert float infinity to
    # integer" (the heartbeat in µs), "the publisher thread failed: OverflowError: timestamp out of range" (its wait)
    ({"replay": "x", "heartbeat_s": 1e308}, "heartbeat-s must be a positive number of at most 10^9 s (got 1e+308)"),
    # accepted, and a still scene's heartbeat came on almost every event (416k frames for a 0.3 s recording)
    ({"replay": "x", "heartbeat_s": 1e-300}, "heartbeat-s must be at least 0.001 s (got 1e-300)"),
    ({"replay": "x", "stats_interval_s": 1e13}, "stats-interval-s must be a positive number of at most 10^9 s"),
    ({"replay": "x", "frobnicate": 1}, "unknown option(s) frobnicate"),
    ({"replay": "x", "log_level": "loud"}, "log-level"),
    # TOML switches written as strings or numbers would be "true" to Python: a usage error instead
    ({"replay": "x", "loop": "false"}, "loop must be true or false (got 'false')"),
    ({"device": "auto", "reconnect": 0}, "reconnect must be true or false (got 0)"),
    ({"replay": "x", "no_publish": "no"}, "no-publish must be true or false (got 'no')"),
    ({"replay": "x", "c": True}, "expected a number, not true"),
    ({"replay": "x", "speed": False}, "expected a number, not false"),
])
def test_invalid_values_name_the_key_and_the_value(options, fragment):
    with pytest.raises(ConfigError) as info:
        NodeConfig.from_options(options)
    assert fragment in str(info.value)
    assert info.value.exit_code == 2


@pytest.mark.parametrize("flag", ["out", "record", "save_calibration"])
def test_outputs_never_overwrite_the_curve_secret_key(tmp_path: Path, flag):
    # '--curve-secret-key keys/server.key_secret --out keys/server.key_secret' replaced the secret key at start
    key = tmp_path / "server.key_secret"
    key.write_text("a secret")
    with pytest.raises(ConfigError, match="would overwrite the curve-secret-key file"):
        NodeConfig.from_options({"replay": "x.aedat4", "curve_secret_key": str(key), flag: str(key)})
    assert key.read_text() == "a secret"


@pytest.mark.parametrize("flag", ["out", "record", "save_calibration"])
def test_outputs_never_overwrite_the_input_recording(tmp_path: Path, monkeypatch, flag):
    # `--replay rec.aedat4 --out rec.aedat4` emptied the user's recording before reading it; `--save-calibration
    # rec.aedat4` replaced it with the calibration's JSON at the end of the run
    name = flag.replace("_", "-")
    rec = tmp_path / "rec.aedat4"
    rec.write_bytes(b"a recording")
    (tmp_path / "link.aedat4").symlink_to(rec)
    monkeypatch.chdir(tmp_path)
    for written in ("rec.aedat4", str(rec), "./rec.aedat4", "link.aedat4"):
        with pytest.raises(ConfigError, match=f"{name} would overwrite the replay recording"):
            NodeConfig.from_options({"replay": str(rec), flag: written})
    with pytest.raises(ConfigError, match="overwrite the emulate-from recording"):
        NodeConfig.from_options({"device": "davis240", "usb_backend": "drivers.emulator:backend",
                                 "emulate_from": "rec.aedat4", flag: str(rec)})
    assert NodeConfig.from_options({"replay": str(rec), flag: "other.aedat4"}).output is not None
    assert rec.read_bytes() == b"a recording"


@pytest.mark.parametrize("a, b", [("out", "save_calibration"), ("record", "save_calibration"), ("out", "record")])
def test_written_files_are_apart_however_spelled(tmp_path: Path, monkeypatch, a, b):
    # `--out sharp.aedat4 --save-calibration ./sharp.aedat4` replaced every written frame with the calibration
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match="must be different files"):
        NodeConfig.from_options({"replay": "x.aedat4", a: "f.aedat4", b: str(tmp_path / "f.aedat4")})


@pytest.mark.parametrize("flag", ["out", "record"])
def test_outputs_never_overwrite_the_calibration_read(tmp_path: Path, flag):
    cal = tmp_path / "cal.json"
    with pytest.raises(ConfigError, match=f"{flag} would overwrite the calibration file"):
        NodeConfig.from_options({"replay": "x.aedat4", "calibration": str(cal), flag: str(cal)})


def test_a_calibration_may_be_saved_over_the_one_it_started_from(tmp_path: Path):
    cal = tmp_path / "cal.json"
    cfg = NodeConfig.from_options({"replay": "x.aedat4", "calibration": str(cal), "save_calibration": str(cal)})
    assert cfg.save_calibration == cfg.calibration == cal


def test_no_publish_empties_the_endpoints():
    cfg = NodeConfig.from_options({"replay": "x", "no_publish": True})
    assert not cfg.publisher.enabled


@pytest.mark.parametrize("endpoint", ["tcp://127.0.0.1:1", "tcp://127.0.0.1:65535", "tcp://*:*", "tcp://[::1]:5555",
                                      "ipc:///tmp/edi.sock"])
def test_valid_endpoints_are_accepted(endpoint):
    assert NodeConfig.from_options({"replay": "x", "publish": [endpoint]}).publisher.endpoints == (endpoint,)


def test_a_no_publish_flag_overrides_publish_from_the_file():
    merged = merge_options({"replay": "a.aedat4", "publish": ["tcp://127.0.0.1:6000"]}, {"no_publish": True})
    assert not NodeConfig.from_options(merged).publisher.enabled


def test_toml_uses_the_flag_names_and_flags_override_it(tmp_path: Path):
    path = tmp_path / "edi.toml"
    path.write_text('replay = "rec.aedat4"\nspeed = 0\nevery = 500\nc-on = 0.2\nc_off = 0.3\n'
                    'publish = ["tcp://127.0.0.1:6000", "ipc:///tmp/edi"]\nmode = "nearest"\n')
    file_cfg = NodeConfig.from_toml(path)
    assert file_cfg.source.replay == tmp_path / "rec.aedat4"  # relative to the config file
    assert file_cfg.source.speed == 0 and file_cfg.edi.every == 500
    assert (file_cfg.edi.c_on, file_cfg.edi.c_off) == (0.2, 0.3)
    assert file_cfg.publisher.endpoints == ("tcp://127.0.0.1:6000", "ipc:///tmp/edi")
    flagged = NodeConfig.from_toml(path, {"every": 2000, "mode": "causal"})
    assert flagged.edi.every == 2000 and flagged.edi.mode == "causal"  # flags win
    assert flagged.edi.c_on == 0.2  # the file still beats the defaults
    assert NodeConfig.from_options({"replay": "x"}).edi.every != 500


def test_a_device_flag_replaces_a_replay_from_the_file():
    merged = merge_options({"replay": "a.aedat4", "no_publish": True}, {"device": "auto", "publish": ["tcp://*:1"]})
    cfg = NodeConfig.from_options(merged)
    assert cfg.source.device == "auto" and cfg.source.replay is None
    assert cfg.publisher.endpoints == ("tcp://*:1",)


_TOML_VALUES = st.one_of(st.none(), st.booleans(), st.integers(-2**80, 2**80), st.floats(), st.text(max_size=6),
                         st.lists(st.one_of(st.text(max_size=6), st.integers()), max_size=3),
                         st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))


@settings(max_examples=400, deadline=None)
@given(st.dictionaries(st.sampled_from(sorted(OPTION_KEYS)), _TOML_VALUES, max_size=6))
def test_fuzzed_option_values_give_a_config_or_a_config_error(options):
    """Any value for any key (as a TOML file or flags could give): a NodeConfig or one ConfigError (exit 2)."""
    try:
        NodeConfig.from_options(options)
    except ConfigError as exc:
        assert exc.exit_code == 2 and "\n" not in str(exc)


def test_config_is_frozen():
    cfg = NodeConfig.from_options({"replay": "x"})
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.edi.every = 3  # type: ignore[misc]


def test_deblur_thread_is_automatic_but_can_be_forced():
    assert NodeConfig.from_options({"replay": "x", "speed": 0}).effective_edi.deblur_thread is False
    assert NodeConfig.from_options({"replay": "x"}).effective_edi.deblur_thread is True
    assert NodeConfig.from_options({"device": "auto"}).effective_edi.deblur_thread is True
    forced = NodeConfig.from_options({"replay": "x", "speed": 0, "deblur_thread": True})
    assert forced.effective_edi.deblur_thread is True
    with pytest.raises(ConfigError, match="deblur-thread must be true or false"):
        NodeConfig.from_options({"replay": "x", "deblur_thread": "yes"})


def test_dv_keys_come_from_toml_and_dv_input_is_one_of_the_inputs(tmp_path):
    from edi_live.config import NodeConfig, read_toml
    from edi_live.errors import ConfigError as _ConfigError

    path = tmp_path / "dv.toml"
    path.write_text('dv-input = ["tcp://127.0.0.1:7777", "frames=tcp://127.0.0.1:7778"]\n'
                    'dv-output = "tcp://127.0.0.1:7779"\ndv-output-events = "tcp://127.0.0.1:7780"\n')
    config = NodeConfig.from_options(read_toml(path))
    assert config.source.dv_input == ("tcp://127.0.0.1:7777", "frames=tcp://127.0.0.1:7778")
    assert config.source.kind == "dv" and config.ring_policy == "drop_oldest"  # live: never block the receiver
    assert (config.output.dv_output, config.output.dv_output_events) == ("tcp://127.0.0.1:7779",
                                                                          "tcp://127.0.0.1:7780")
    with pytest.raises(_ConfigError, match="choose one input"):
        NodeConfig.from_options({"dv_input": ["tcp://127.0.0.1:7777"], "replay": "x.aedat4"})


def test_gray_is_a_switch_from_the_flag_or_the_config_file(tmp_path: Path):
    from edi_live.cli import options_from_args

    toml = tmp_path / "c.toml"
    toml.write_text('replay = "x.aedat4"\ngray = true\n')
    assert NodeConfig.from_toml(toml).edi.gray is True
    assert NodeConfig.from_options({"replay": "x.aedat4"}).edi.gray is False
    assert options_from_args(["--replay", "x.aedat4", "--gray"])[0]["gray"] is True
    assert "gray" not in options_from_args(["--replay", "x.aedat4"])[0]  # the file's value stands
    with pytest.raises(ConfigError, match="gray must be true or false"):
        NodeConfig.from_options({"replay": "x.aedat4", "gray": "yes"})


def test_the_flicker_mask_switch_reaches_the_reconstructor():
    from edi_live.node import default_reconstructor

    def masked(**options):
        cfg = NodeConfig.from_options({"device": "auto", **options})
        return default_reconstructor(16, 12, cfg.edi).settings.mask_flicker_pixels

    assert masked() is True and masked(mode="nearest") is True
    assert masked(mode="fused") is False  # its next frame takes the drift out; the mask would cost it
    assert masked(flicker_mask=False) is False and masked(mode="fused", flicker_mask=True) is True
    with pytest.raises(ConfigError, match="flicker-mask must be true or false"):
        NodeConfig.from_options({"device": "auto", "flicker_mask": "false"})  # a TOML string, not a boolean


def test_the_fused_residual_switch_reaches_the_reconstructor():
    from edi_live.node import default_reconstructor

    default = NodeConfig.from_options({"device": "auto", "mode": "fused"})
    plain = NodeConfig.from_options({"device": "auto", "mode": "fused", "fused_residual": False})
    assert default_reconstructor(16, 12, default.edi).settings.fused_residual is True
    assert default_reconstructor(16, 12, plain.edi).settings.fused_residual is False


@pytest.mark.parametrize("key, default", [("divisor_median", True), ("latent_denoise", False)])
def test_a_reconstructor_switch_reaches_the_reconstructor_with_its_default(key, default):
    """The node's default is the library's (and the benchmarks'); the flag and the TOML key flip it; a TOML
    string is refused."""
    from edi_live.cli_parser import build_parser
    from edi_live.node import default_reconstructor
    from edi_live.reconstructor import EdiReconstructor

    flag = key.replace("_", "-")
    flipped = NodeConfig.from_options({"device": "auto", key: not default})
    assert getattr(default_reconstructor(16, 12, NodeConfig.from_options({"device": "auto"}).edi).settings,
                   key) is default
    assert getattr(default_reconstructor(16, 12, flipped.edi).settings, key) is (not default)
    assert getattr(build_parser().parse_args([f"--{'no-' if default else ''}{flag}"]), key) is (not default)
    assert getattr(EdiReconstructor(16, 12).settings, key) is default
    with pytest.raises(ConfigError, match=f"{flag} must be true or false"):
        NodeConfig.from_options({"device": "auto", key: "yes"})


@pytest.mark.parametrize("options, refused", [
    ({"publish": ["tcp://127.0.0.1:5555", "tcp://127.0.0.1:5555"]}, "port 5555 is given twice"),
    ({"dv_output": "tcp://127.0.0.1:7777", "dv_output_events": "tcp://127.0.0.1:7777"},
     "port 7777 is given to --dv-output and --dv-output-events"),
    ({"publish": ["tcp://*:7777"], "dv_output": "tcp://127.0.0.1:7777"}, "port 7777 is given to --publish and"),
    ({"publish": ["tcp://127.0.0.1:5555"], "dv_output": "tcp://127.0.0.2:5555"}, None),  # other hosts
    ({"publish": ["tcp://127.0.0.1:*", "tcp://127.0.0.1:*"]}, None),  # free ports, picked at bind
    ({"publish": ["ipc:///tmp/a", "tcp://127.0.0.1:5556"], "dv_output": "tcp://127.0.0.1:5557"}, None),
])
def test_two_endpoints_on_one_port_are_refused_before_the_bind_blames_another_program(options, refused):
    # the second bind failed with 'address in use', which the node reports as another edi-live holding the port
    if refused is None:
        NodeConfig.from_options({"replay": "x.aedat4", **options})
        return
    with pytest.raises(ConfigError, match=refused):
        NodeConfig.from_options({"replay": "x.aedat4", **options})


def _read_in_thread(path: Path) -> tuple[threading.Thread, list]:
    outcome: list = []

    def read() -> None:
        try:
            outcome.append(read_toml(path))
        except ConfigError as exc:
            outcome.append(exc)

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    return thread, outcome


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_fifo_nothing_writes_to_is_a_config_error_not_a_wait_for_ever(tmp_path: Path, monkeypatch):
    # open() of a FIFO without a writer blocked for ever, and Ctrl-C only set the stop flag (the open is retried)
    monkeypatch.setattr(config_file, "PIPE_WAIT_S", 0.2)
    fifo = tmp_path / "edi.toml"
    os.mkfifo(fifo)
    thread, outcome = _read_in_thread(fifo)
    thread.join(20)
    if thread.is_alive():  # release the blocked open() before failing
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        thread.join(5)
        pytest.fail("reading a FIFO that nothing writes to did not end")
    assert isinstance(outcome[0], ConfigError) and str(fifo) in str(outcome[0]) and "pipe" in str(outcome[0])


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_fifo_is_read_when_its_writer_comes_after_the_reader(tmp_path: Path):
    fifo = tmp_path / "edi.toml"
    os.mkfifo(fifo)
    thread, outcome = _read_in_thread(fifo)
    with open(fifo, "wb") as writer:  # blocks until the reader has the FIFO open
        writer.write(b"every = 500\n")
        writer.flush()
        writer.write(b"speed = 0\n")
    thread.join(20)
    assert outcome == [{"every": 500, "speed": 0}]


def test_a_pipe_whose_writer_is_done_is_read_like_bash_process_substitution(tmp_path: Path):
    with written_pipe(b"every = 250\n") as path:
        assert read_toml(Path(path)) == {"every": 250}


def test_an_ipc_endpoint_never_replaces_a_file(tmp_path: Path):
    # libzmq unlinks whatever is at an ipc:// path before it binds: '--publish ipc:///home/me/notes.txt' deleted
    # the notes and left a socket in their place
    notes = tmp_path / "notes.txt"
    notes.write_text("precious")
    with pytest.raises(ConfigError, match="exists and is not a socket"):
        NodeConfig.from_options({"replay": "x", "publish": [f"ipc://{notes}"]})
    assert notes.read_text() == "precious"
    fresh = f"ipc://{tmp_path / 'edi.sock'}"
    assert NodeConfig.from_options({"replay": "x", "publish": [fresh]}).publisher.endpoints == (fresh,)

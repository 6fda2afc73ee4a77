"""Wire protocol v1 without sockets: encoding matches the contract's keys and values, decoding rejects
everything malformed with ClientError (never a numpy or msgpack exception)."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edi_live import wire
from edi_live.datatypes import Reconstruction
from edi_live.errors import ClientError

CONTRACT_KEYS = {"v", "seq", "t", "w", "h", "dtype", "kind", "ref_t", "exp_start", "exp_end", "n_events",
                 "source"}


def make_rec(rng, w=240, h=180, c_on=0.2, c_off=0.2, kind="latent", dtype=np.uint8) -> Reconstruction:
    image = rng.integers(0, 256, size=(h, w)).astype(dtype)
    return Reconstruction(image=image, t_us=1_700_000_123_456, kind=kind, ref_t_us=1_700_000_100_000,
                          exposure_start_us=1_700_000_095_000, exposure_end_us=1_700_000_105_000,
                          c_on=c_on, c_off=c_off, n_events=1000, arrival_ns=42)


def as_bytes(parts) -> list[bytes]:
    return [bytes(p) for p in parts]


def header_of(parts) -> dict:
    return msgpack.unpackb(bytes(parts[1]), raw=False)  # independent of wire.decode


def test_frame_parts_follow_the_contract(rng):
    rec = make_rec(rng)
    parts = wire.encode_frame(rec, seq=7, source="DAVIS346_00000391")
    assert len(parts) == 3 and bytes(parts[0]) == b"frame"
    header = header_of(parts)
    assert CONTRACT_KEYS <= set(header)
    assert header["v"] == 1 and header["seq"] == 7 and header["source"] == "DAVIS346_00000391"
    assert (header["w"], header["h"], header["dtype"]) == (240, 180, "u1")
    assert (header["t"], header["ref_t"]) == (rec.t_us, rec.ref_t_us)
    assert (header["exp_start"], header["exp_end"]) == (rec.exposure_start_us, rec.exposure_end_us)
    assert header["kind"] == "latent" and header["n_events"] == 1000
    assert header["c"] == pytest.approx(0.2) and "c_on" not in header
    assert bytes(parts[2]) == rec.image.tobytes(order="C")  # raw row-major pixels


def test_separate_thresholds_go_as_c_on_and_c_off(rng):
    header = header_of(wire.encode_frame(make_rec(rng, c_on=0.25, c_off=0.3), 0, "cam"))
    assert "c" not in header
    assert (header["c_on"], header["c_off"]) == pytest.approx((0.25, 0.3))
    assert wire.thresholds(header) == pytest.approx((0.25, 0.3))
    assert wire.thresholds({"c": 0.1}) == (0.1, 0.1)


@pytest.mark.parametrize("kind", ["deblurred", "latent"])
@pytest.mark.parametrize("size", [(240, 180), (346, 260), (1, 1), (17, 3)])
def test_round_trip(rng, kind, size):
    rec = make_rec(rng, *size, kind=kind)
    header, image = wire.decode_frame(as_bytes(wire.encode_frame(rec, 123, "cam")))
    assert image.shape == (size[1], size[0]) and image.dtype == np.uint8
    np.testing.assert_array_equal(image, rec.image)
    assert header["kind"] == kind and header["seq"] == 123


def test_sixteen_bit_pixels_travel_little_endian(rng):
    rec = make_rec(rng, 8, 4, dtype=np.dtype(">u2"))
    parts = wire.encode_frame(rec, 0, "cam")
    assert header_of(parts)["dtype"] == "<u2"
    _, image = wire.decode_frame(as_bytes(parts))
    np.testing.assert_array_equal(image, rec.image.astype(np.uint16))


def test_a_non_contiguous_image_is_sent_row_major(rng):
    big = rng.integers(0, 256, size=(20, 30), dtype=np.uint8)
    rec = make_rec(rng)
    rec = Reconstruction(big[::2, ::3], rec.t_us, "latent", 0, 0, 0, 0.2, 0.2, 0)
    _, image = wire.decode_frame(as_bytes(wire.encode_frame(rec, 0, "cam")))
    np.testing.assert_array_equal(image, big[::2, ::3])


def test_unsupported_pixel_dtype_is_refused_on_encode(rng):
    rec = make_rec(rng, 4, 4)
    rec = Reconstruction(rec.image.astype(np.float64), 0, "latent", 0, 0, 0, 0.2, 0.2, 0)
    with pytest.raises(ValueError, match="cannot go on the wire"):
        wire.encode_frame(rec, 0, "cam")


def good_parts(rng, **header_changes):
    parts = as_bytes(wire.encode_frame(make_rec(rng, 16, 8), 5, "cam"))
    header = msgpack.unpackb(parts[1], raw=False)
    for key, value in header_changes.items():
        if value is KeyError:
            header.pop(key)
        else:
            header[key] = value
    parts[1] = msgpack.packb(header)
    return parts


@pytest.mark.parametrize("changes, message", [
    ({"v": 3}, "protocol v3"),
    ({"v": KeyError}, "version"),
    ({"seq": -1}, "seq"),
    ({"seq": 1.5}, "seq"),
    ({"t": True}, "'t'"),
    ({"t": KeyError}, "'t'"),
    ({"w": 0}, "positive"),
    ({"h": "180"}, "'h'"),
    ({"w": 17}, "pixel part has"),
    ({"dtype": "f8"}, "dtype"),
    ({"dtype": KeyError}, "dtype"),
    ({"kind": "aps"}, "kind"),
    ({"source": 3}, "source"),
    ({"c": float("nan")}, "finite"),
    ({"c": KeyError}, "c_on"),
    ({"n_events": KeyError}, "n_events"),
])
def test_bad_headers_are_rejected(rng, changes, message):
    with pytest.raises(ClientError, match=message):
        wire.decode_frame(good_parts(rng, **changes))


@pytest.mark.parametrize("mutate, message", [
    (lambda p: p[:2], "3 parts"),
    (lambda p: p + [b""], "3 parts"),
    (lambda p: [b"stats"] + p[1:], "topic"),
    (lambda p: [p[0], b"\xc1garbage", p[2]], "not valid msgpack"),
    (lambda p: [p[0], msgpack.packb([1, 2]), p[2]], "expected a map"),
    (lambda p: [p[0], msgpack.packb({1: 2}), p[2]], "not valid msgpack"),
    (lambda p: [p[0], p[1] + b"\x00", p[2]], "not valid msgpack"),
    (lambda p: [p[0], p[1], p[2][:-1]], "pixel part has"),
    (lambda p: [p[0], b"\x00" * (wire.MAX_HEADER_BYTES + 1), p[2]], "limit"),
    (lambda p: [p[0], p[1], 12345], "not a byte buffer"),
])
def test_malformed_messages_are_rejected(rng, mutate, message):
    with pytest.raises(ClientError, match=message):
        wire.decode_frame(mutate(good_parts(rng)))


def test_oversized_messages_are_rejected(rng):
    parts = as_bytes(wire.encode_frame(make_rec(rng, 240, 180), 0, "cam"))
    with pytest.raises(ClientError, match="exceeds the limit"):
        wire.decode_frame(parts, max_bytes=240 * 180)
    wire.decode_frame(parts, max_bytes=sum(map(len, parts)))  # exactly at the limit is fine


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=64), min_size=0, max_size=4), st.data())
def test_fuzzed_parts_give_only_client_errors(parts, data):
    if len(parts) >= 2 and data.draw(st.booleans()):
        parts[0] = b"frame"
    try:
        wire.decode_frame(parts)
    except ClientError:
        pass


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.sampled_from(sorted(CONTRACT_KEYS | {"c", "c_on", "c_off"})),
                       st.one_of(st.integers(-2**70, 2**70), st.floats(), st.text(max_size=4), st.none(),
                                 st.booleans(), st.binary(max_size=4))),
       st.binary(max_size=64))
def test_fuzzed_headers_give_only_client_errors(header, pixels):
    try:
        packed = msgpack.packb(header)
    except (OverflowError, ValueError):
        return
    try:
        wire.decode_frame([b"frame", packed, pixels])
    except ClientError:
        pass


def test_stats_round_trip_with_units_version_and_numpy_values():
    stats = {"events_per_s": np.float32(1.5e6), "frames_per_s": 1500.0, "c": np.float64(0.21),
             "reestimations": np.int64(3), "ring_occupancy": 0.25, "latency_p99_us": None, "sent": 9,
             "dropped": 2, "nested": {"a": np.int32(1)}, "weird": object()}
    parts = wire.encode_stats(stats)
    assert len(parts) == 2 and parts[0] == b"stats"
    decoded = wire.decode_stats(parts)
    raw = msgpack.unpackb(parts[1], raw=False)
    assert decoded == raw
    assert decoded["v"] == 1
    assert decoded["events_per_s"] == pytest.approx(1.5e6)
    assert decoded["reestimations"] == 3 and decoded["ring_occupancy"] == 0.25
    assert decoded["frames_sent"] == 9 and decoded["publish_dropped"] == 2  # code names mapped to wire keys
    assert "sent" not in decoded and decoded["latency_p99_us"] is None
    assert decoded["nested"] == {"a": 1} and isinstance(decoded["weird"], str)


@pytest.mark.parametrize("parts, message", [
    ([b"stats"], "2 parts"),
    ([b"frame", msgpack.packb({"v": 1})], "topic"),
    ([b"stats", msgpack.packb({"v": 9})], "v9"),
    ([b"stats", msgpack.packb({"v": True})], "protocol"),
    ([b"stats", b"\xff\xff"], "msgpack"),
    ([b"stats", msgpack.packb("x")], "map"),
])
def test_bad_stats_are_rejected(parts, message):
    with pytest.raises(ClientError, match=message):
        wire.decode_stats(parts)


def test_decoded_numbers_stay_finite(rng):
    header, _ = wire.decode_frame(as_bytes(wire.encode_frame(make_rec(rng, 4, 4, 0.01, 2.0), 0, "cam")))
    assert all(math.isfinite(header[k]) for k in ("c_on", "c_off"))


# The frame header table of the README ("The wire protocol"), written out here independently of edi_live.wire:
# key -> (type, value expected for make_rec(..., c_on=0.2, c_off=0.4) sent as seq 9 from "DAVIS346_00000391").
README_FRAME_TABLE = {
    "v": (int, 1),
    "layout": (str, "gray"),
    "channels": (int, 1),
    "seq": (int, 9),
    "t": (int, 1_700_000_123_456),
    "w": (int, 5),
    "h": (int, 3),
    "dtype": (str, "u1"),
    "kind": (str, "latent"),
    "c": (float, None),  # only when ON and OFF thresholds are equal
    "c_on": (float, 0.2),
    "c_off": (float, 0.4),
    "ref_t": (int, 1_700_000_100_000),
    "exp_start": (int, 1_700_000_095_000),
    "exp_end": (int, 1_700_000_105_000),
    "n_events": (int, 1000),
    "source": (str, "DAVIS346_00000391"),
}


def test_the_header_is_the_documented_table(rng):
    header = header_of(wire.encode_frame(make_rec(rng, 5, 3, c_on=0.2, c_off=0.4), 9, "DAVIS346_00000391"))
    assert set(header) == set(README_FRAME_TABLE) - {"c"}
    for key, value in header.items():
        kind, expected = README_FRAME_TABLE[key]
        assert type(value) is kind, (key, value)
        assert value == pytest.approx(expected), key
    same = header_of(wire.encode_frame(make_rec(rng, 5, 3, c_on=0.25, c_off=0.25), 9, "DAVIS346_00000391"))
    assert set(same) == set(README_FRAME_TABLE) - {"c_on", "c_off"} and same["c"] == pytest.approx(0.25)


def test_the_readme_documents_exactly_these_keys(repo_root):
    text = (repo_root / "README.md").read_text()
    table = text.split("## The wire protocol", 1)[1].split("**Frames**", 1)[1].split("**Stats**", 1)[0]
    documented = set()
    for line in table.splitlines():
        cells = line.split("|")
        if len(cells) > 2 and "`" in cells[1]:
            documented.update(cells[1].split("`")[1::2])
    assert documented == set(README_FRAME_TABLE)


_MSGPACK_VALUES = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(), st.text(max_size=8),
              st.binary(max_size=8), st.builds(msgpack.ExtType, st.integers(0, 127), st.binary(max_size=4))),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=4), inner, max_size=4)),
    max_leaves=12)


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(st.text(max_size=8), _MSGPACK_VALUES, max_size=6), st.booleans())
def test_fuzzed_stats_maps_decode_or_give_client_errors(extra, with_version):
    """Any msgpack map, with any values (binary, ext types, nesting): a dict or one ClientError."""
    stats = dict(extra, v=1) if with_version else extra
    parts = [b"stats", msgpack.packb(stats, use_bin_type=True)]
    try:
        decoded = wire.decode_stats(parts)
    except ClientError:
        assert not with_version or len(parts[1]) > wire.MAX_HEADER_BYTES
        return
    assert isinstance(decoded, dict) and decoded["v"] == 1


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 255)), min_size=1, max_size=6),
       st.integers(0, 2))
def test_bit_flipped_frames_decode_consistently_or_give_client_errors(flips, part):
    """A valid frame with bytes flipped in one part: either a frame whose image matches its header, or a
    ClientError (never a numpy, msgpack or unicode exception)."""
    parts = [bytearray(p) for p in as_bytes(wire.encode_frame(make_rec(np.random.default_rng(1), 12, 8), 3, "cam"))]
    for where, xor in flips:
        parts[part][where % len(parts[part])] ^= xor
    try:
        header, image = wire.decode_frame([bytes(p) for p in parts])
    except ClientError:
        return
    assert image.shape == (header["h"], header["w"]) and image.dtype == wire.DTYPES[header["dtype"]]


def make_colour_rec(rng, w=6, h=4) -> Reconstruction:
    rec = make_rec(rng, w, h)
    image = rng.integers(0, 256, size=(h, w, 3)).astype(np.uint8)
    return Reconstruction(image, rec.t_us, rec.kind, rec.ref_t_us, rec.exposure_start_us, rec.exposure_end_us,
                          rec.c_on, rec.c_off, rec.n_events, rec.arrival_ns)


def test_colour_frames_are_v2_bgr_and_decode_to_h_w_3(rng):
    rec = make_colour_rec(rng)
    parts = wire.encode_frame(rec, seq=1, source="DAVIS346_1")
    header = header_of(parts)
    assert (header["v"], header["layout"], header["channels"], header["w"], header["h"]) == (2, "bgr", 3, 6, 4)
    assert bytes(parts[2]) == rec.image.tobytes()  # row-major, B, G, R interleaved
    assert np.shares_memory(np.frombuffer(parts[2], np.uint8), rec.image)  # still zero-copy
    decoded, image = wire.decode_frame(as_bytes(parts))
    assert image.shape == (4, 6, 3) and np.array_equal(image, rec.image) and decoded["layout"] == "bgr"
    # the v1 rule every v1 client applies (`v` must equal 1): it refuses a colour frame, never misreads it
    assert header["v"] != 1 and header_of(wire.encode_frame(make_rec(rng, 6, 4), 2, "x"))["v"] == 1


def test_a_v1_senders_frame_without_layout_is_gray(rng):
    header, image = wire.decode_frame(good_parts(rng, layout=KeyError, channels=KeyError))
    assert header["layout"] == "gray" and image.ndim == 2


@pytest.mark.parametrize("changes, message", [
    ({"layout": "rgb"}, "layout 'rgb'"),
    ({"layout": "bgr", "channels": 3}, "16x8x3 u1 = 384 bytes, pixel part has 128"),  # gray-sized pixels
    ({"layout": "bgr"}, "layout .bgr. with 1 channels"),
    ({"channels": 3}, "layout 'gray' with 3 channels"),
])
def test_bad_layouts_are_rejected(rng, changes, message):
    with pytest.raises(ClientError, match=message):
        wire.decode_frame(good_parts(rng, **changes))


@pytest.mark.parametrize("changes, message", [
    ({"layout": ["bgr"]}, r"layout \['bgr'\]"),  # unhashable values: a TypeError from `in` before
    ({"layout": {"bgr": 3}}, "layout {'bgr': 3}"),
    ({"dtype": ["u1"]}, r"dtype \['u1'\]"),
    ({"dtype": {}}, "dtype {}"),
    ({"channels": 1.0}, "1.0 channels"),  # 1.0 == 1: it reached the reshape, a TypeError for 3.0
    ({"channels": True}, "True channels"),
    ({"v": 0}, "v0 is not one edi-live sends"),  # not "upgrade edi-live": no version would read it
    ({"v": -1}, "v-1 is not one edi-live sends"),
])
def test_header_values_of_the_wrong_type_are_client_errors(rng, changes, message):
    with pytest.raises(ClientError, match=message):
        wire.decode_frame(good_parts(rng, **changes))


def test_a_colour_frame_whose_channels_is_a_float_is_a_client_error(rng):
    parts = as_bytes(wire.encode_frame(make_colour_rec(rng), 1, "cam"))
    header = msgpack.unpackb(parts[1], raw=False)
    header["channels"] = 3.0
    with pytest.raises(ClientError, match="'bgr' with 3.0 channels"):
        wire.decode_frame([parts[0], msgpack.packb(header), parts[2]])


def test_the_cached_header_encoder_gives_exactly_the_reference_bytes(rng):
    """FrameEncoder packs from per-layout templates; every message must equal encode_frame's, whatever mix of
    layouts, kinds, thresholds and number types goes through one encoder."""
    encoder = wire.FrameEncoder("DAVIS346_00000391")
    base = make_rec(rng)
    recs = [base, make_rec(rng, kind="deblurred"), make_rec(rng, c_on=0.25, c_off=0.3), make_rec(rng, 346, 260),
            make_rec(rng, 8, 4, dtype=np.dtype(">u2")), make_rec(rng, 8, 4, dtype=np.dtype("<f4")),
            Reconstruction(rng.integers(0, 256, (20, 30), dtype=np.uint8)[::2, ::3], 5, "latent", 0, 0, 0,
                           0.2, 0.2, 0),
            Reconstruction(base.image, np.int64(2**40), "latent", np.int64(-7), 0, 2**63 - 1, np.float32(0.125),
                           np.float32(0.125), np.uint16(3)),
            Reconstruction(base.image, 0, "latent", 0, -(2**31), 0, 1e-30, 2.5, 0), base, make_colour_rec(rng),
            make_colour_rec(rng, 346, 260), base]
    for seq, rec in enumerate(recs * 2):
        seq = seq * 1_000_003  # seq values of every msgpack integer width
        assert as_bytes(encoder.encode(rec, seq)) == as_bytes(wire.encode_frame(rec, seq, "DAVIS346_00000391"))


def test_the_cached_header_encoder_refuses_what_the_wire_cannot_carry(rng):
    rec = make_rec(rng, 4, 4)
    rec = Reconstruction(rec.image.astype(np.float64), 0, "latent", 0, 0, 0, 0.2, 0.2, 0)
    with pytest.raises(ValueError, match="cannot go on the wire"):
        wire.FrameEncoder("cam").encode(rec, 0)

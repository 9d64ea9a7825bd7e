"""Insole packet codec: round trips, limits, and fuzzing (malformed -> counted, never a crash)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from selfcal.gateway import codec

SETTINGS = settings(max_examples=300, deadline=None, derandomize=True)


@st.composite
def packet_counts(draw):
    """Integer field values of a valid packet."""
    n = draw(st.integers(1, 40))
    acc = draw(st.lists(st.integers(-32768, 32767), min_size=3 * n, max_size=3 * n))
    prs = draw(st.lists(st.integers(0, 4095), min_size=4 * n, max_size=4 * n))
    seq = draw(st.integers(0, 2**32 - 1))
    temp = draw(st.one_of(st.none(), st.integers(-32768, 32767)))
    return seq, np.array(acc).reshape(n, 3), np.array(prs).reshape(n, 4), temp


@SETTINGS
@given(packet_counts())
def test_packet_round_trip_is_exact_on_the_lsb_grid(fields):
    seq, acc_counts, p_counts, temp_counts = fields
    acc_g = acc_counts / codec.ACC_COUNTS_PER_G
    pressure_kpa = p_counts * codec.PRESSURE_KPA_PER_COUNT
    temp_c = None if temp_counts is None else temp_counts * codec.TEMP_C_PER_COUNT
    data = codec.encode_packet(seq, acc_g, pressure_kpa, temp_c)
    assert len(data) == codec.HEADER_SIZE_BYTES + codec.SAMPLE_SIZE_BYTES * len(acc_g)
    packet = codec.decode_packet(data)
    assert packet.seq == seq
    np.testing.assert_array_equal(packet.acc_g, acc_g)
    np.testing.assert_array_equal(packet.pressure_kpa, pressure_kpa)
    if temp_c is None:
        assert np.isnan(packet.temp_c)
    else:
        assert packet.temp_c == pytest.approx(temp_c, abs=1e-9)
    # bytes -> values -> bytes is the identity
    assert codec.encode_packet(packet.seq, packet.acc_g, packet.pressure_kpa, packet.temp_c) == data


@SETTINGS
@given(
    st.integers(1, 19),
    st.floats(-7.9, 7.9),
    st.floats(0.0, 1023.0),
    st.floats(-300.0, 300.0),
    st.integers(0, 2**32 - 1),
)
def test_physical_values_round_trip_within_half_an_lsb(n, a, p, t, seq):
    rng = np.random.default_rng(n)
    acc_g = np.clip(a + rng.normal(0, 0.05, size=(n, 3)), -7.99, 7.99)
    pressure_kpa = np.clip(p + rng.normal(0, 1.0, size=(n, 4)), 0.0, 1023.0)
    packet = codec.decode_packet(codec.encode_packet(seq, acc_g, pressure_kpa, t))
    assert np.max(np.abs(packet.acc_g - acc_g)) <= 0.5 / codec.ACC_COUNTS_PER_G + 1e-12
    assert np.max(np.abs(packet.pressure_kpa - pressure_kpa)) <= 0.5 * codec.PRESSURE_KPA_PER_COUNT + 1e-9
    assert abs(packet.temp_c - t) <= 0.5 * codec.TEMP_C_PER_COUNT + 1e-9


def test_out_of_range_values_saturate():
    packet = codec.decode_packet(
        codec.encode_packet(0, [[9.0, -9.0, np.nan]], [[-5.0, 2000.0, np.nan, 1.0]], 400.0)
    )
    np.testing.assert_array_equal(packet.acc_g, [[32767 / 4096, -8.0, 0.0]])
    np.testing.assert_array_equal(packet.pressure_kpa, [[0.0, 1023.75, 0.0, 1.0]])
    assert packet.temp_c == pytest.approx(327.67)


def test_one_sample_fits_the_default_att_payload_and_larger_mtus_pack_more():
    data = codec.encode_packet(7, np.zeros((1, 3)), np.zeros((1, 4)), 20.0)
    assert len(data) == codec.DEFAULT_ATT_PAYLOAD_BYTES == 20
    assert codec.samples_per_packet(23) == 1
    assert codec.samples_per_packet(247) == 19
    assert codec.samples_per_packet(247, cap=10) == 10
    assert codec.samples_per_packet(517) == 42
    with pytest.raises(codec.CodecError, match="att_mtu"):
        codec.samples_per_packet(22)


def _valid(n: int = 2) -> bytes:
    return codec.encode_packet(1, np.zeros((n, 3)), np.zeros((n, 4)), 25.0)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"", "shorter than"),
        (_valid()[:19], "shorter than"),
        (_valid()[:-1], "does not match n=2"),
        (_valid() + b"\x00", "does not match n=2"),
        (bytes([0x21]) + _valid()[1:], "version 2"),
        (bytes([0x13]) + _valid()[1:], "reserved flag"),
        (_valid()[:1] + b"\x00" + _valid()[2:], "n is 0"),
    ],
)
def test_malformed_packets_are_rejected_with_the_reason(data, message):
    with pytest.raises(codec.MalformedPacketError, match=message):
        codec.decode_packet(data)


@SETTINGS
@given(st.binary(max_size=600))
def test_fuzz_arbitrary_bytes_decode_or_raise_malformed_only(data):
    try:
        packet = codec.decode_packet(data)
    except codec.MalformedPacketError:
        return
    assert len(data) == 8 + 12 * packet.n
    assert packet.acc_g.shape == (packet.n, 3) and packet.pressure_kpa.shape == (packet.n, 4)
    assert np.all(np.abs(packet.acc_g) <= 8.0) and np.all(packet.pressure_kpa >= 0)


@SETTINGS
@given(packet_counts(), st.data())
def test_fuzz_mutated_valid_packets_never_crash(fields, data):
    seq, acc_counts, p_counts, _ = fields
    buf = bytearray(
        codec.encode_packet(seq, acc_counts / 4096.0, p_counts * 0.25, 21.0)
    )
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["flip", "truncate", "extend"]))
        if op == "flip" and buf:
            i = data.draw(st.integers(0, len(buf) - 1))
            buf[i] ^= data.draw(st.integers(1, 255))
        elif op == "truncate" and buf:
            del buf[data.draw(st.integers(0, len(buf) - 1)) :]
        else:
            buf += data.draw(st.binary(min_size=1, max_size=24))
    try:
        packet = codec.decode_packet(bytes(buf))
    except codec.MalformedPacketError:
        return
    assert len(buf) == 8 + 12 * packet.n


def test_non_bytes_input_is_malformed_not_a_crash():
    with pytest.raises(codec.MalformedPacketError, match="bytes-like"):
        codec.decode_packet(12345)  # type: ignore[arg-type]


@SETTINGS
@given(
    st.from_regex(r"[A-Za-z0-9][A-Za-z0-9._:-]{0,63}", fullmatch=True),
    st.text(max_size=60),
    st.integers(1, 65535),
    st.integers(1, 255),
)
def test_info_round_trip(device_id, firmware, rate_centi_hz, max_n):
    info = codec.DeviceInfo(device_id, firmware, rate_centi_hz / 100.0, max_n)
    assert codec.decode_info(codec.encode_info(info)) == info


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"\x01\x01", "truncated"),
        (b"\x02\x01\xd0\x07\x0a\x00\x01a", "info version 2"),
        (b"\x01\x02\xd0\x07\x0a\x00\x01a", "packet version 2"),
        (b"\x01\x01\x00\x00\x0a\x00\x01a", "0 Hz"),
        (b"\x01\x01\xd0\x07\x0a\x00\x05a", "runs past"),
        (b"\x01\x01\xd0\x07\x0a\x00\x01a!", "trailing"),
        (b"\x01\x01\xd0\x07\x0a\x00\x02a/", "device_id"),
    ],
)
def test_malformed_info_records_are_rejected(data, message):
    with pytest.raises(codec.MalformedPacketError, match=message):
        codec.decode_info(data)


def test_control_command_round_trip_and_rejections():
    assert codec.decode_control(codec.encode_control(7)) == 7
    for bad in (b"", b"\x02\x05", b"\x01\x00", b"\x01\x05\x00"):
        with pytest.raises(codec.MalformedPacketError):
            codec.decode_control(bad)
    with pytest.raises(codec.CodecError, match="max_samples_per_packet"):
        codec.encode_control(0)


def test_seq_tracker_gaps_wraps_and_restarts():
    tracker = codec.SeqTracker()
    assert tracker.feed(100, 10) == (100, 0, False)
    assert tracker.feed(110, 10) == (110, 0, False)
    assert tracker.feed(125, 5) == (125, 5, False)  # 5 samples lost
    # wrap of the uint32 index: counts keep growing
    tracker = codec.SeqTracker()
    tracker.feed(2**32 - 10, 10)
    assert tracker.feed(0, 10) == (2**32, 0, False)
    assert tracker.feed(20, 10) == (2**32 + 20, 10, False)
    # reboot: the index restarts at 0, the count continues (t_s never goes back)
    tracker = codec.SeqTracker()
    tracker.feed(5000, 10)
    first, lost, restarted = tracker.feed(0, 10)
    assert (first, lost, restarted) == (5010, 0, True)
    assert tracker.feed(10, 10) == (5020, 0, False)


def test_seq_tracker_resumes_from_persisted_state():
    a = codec.SeqTracker()
    a.feed(0, 10)
    a.feed(0, 10)  # restart -> offset
    b = codec.SeqTracker(a.last_count, a.offset)
    assert b.feed(10, 10) == a.feed(10, 10)


def test_header_layout_is_the_documented_one():
    data = codec.encode_packet(0x01020304, [[1.0, -1.0, 0.5]], [[0.25, 0.5, 1.0, 1023.75]], -1.5)
    vf, n, seq, temp = struct.unpack_from("<BBIh", data)
    assert (vf, n, seq, temp) == (0x11, 1, 0x01020304, -150)
    assert struct.unpack_from("<3h", data, 8) == (4096, -4096, 2048)
    packed = int.from_bytes(data[14:20], "little")
    assert [(packed >> s) & 0xFFF for s in (0, 12, 24, 36)] == [1, 2, 4, 4095]

"""The insole BLE protocol: GATT layout, sample packets and the info record.

Pure numpy; no BLE library is imported here, so the codec is usable (and
testable) anywhere.

GATT layout
-----------
One primary service, :data:`SERVICE_UUID`, advertised by the insole, with two
characteristics:

* **data** (:data:`DATA_CHAR_UUID`, *notify* only): sample packets, one per
  notification (format below). Reading it is answered with the ATT error
  *Read Not Permitted*.
* **control/info** (:data:`CONTROL_CHAR_UUID`, *read*, *write*): reading
  returns the info record (firmware, sample rate, device id); writing a
  control command changes the streaming (see :func:`encode_control`).

Sample packet (version 1), little-endian
----------------------------------------
====== ====== =========================================================
offset  size  field
====== ====== =========================================================
0       1     ``version << 4 | flags``; version = 1; flag bit 0 =
              temperature valid; flag bits 1-3 reserved (must be 0)
1       1     ``n``: samples in this packet, 1 <= n <= 255
2       4     ``seq``: uint32 index of the first sample since power-on
              (device time: ``t_s = seq / sample_rate_hz``); the k-th
              sample of the packet has index ``seq + k``; wraps at 2**32
6       2     temperature, int16, 0.01 °C per LSB (one per packet)
8      12*n   n sample records
====== ====== =========================================================

Sample record (12 bytes):

* ``ax, ay, az``: 3 x int16, **1/4096 g per LSB** (range ±8 g, saturating);
* pressure ``p1..p4``: 4 x uint12 packed in 6 bytes as the 48-bit
  little-endian integer ``p1 | p2 << 12 | p3 << 24 | p4 << 36``,
  **0.25 kPa per LSB** (range 0..1023.75 kPa, saturating).

A packet of one sample is 20 bytes, so it fits the default ATT payload
(MTU 23); with a larger MTU the insole packs
``(mtu - 3 - 8) // 12`` samples (19 at MTU 247). A packet whose length,
version, reserved bits or count do not match is *malformed*:
:func:`decode_packet` raises :class:`MalformedPacketError` and never anything
else.

Info record (version 1), little-endian
--------------------------------------
``u8 info_version (=1), u8 packet_version (=1), u16 sample_rate (0.01 Hz per
LSB), u8 max_samples_per_packet, u8 len + firmware (UTF-8), u8 len +
device_id (ASCII: a letter or digit, then up to 63 of [A-Za-z0-9._:-], as the service)``.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

import numpy as np

from selfcal.errors import SelfcalError

#: The insole's primary GATT service (advertised).
SERVICE_UUID = "5e1fca10-0001-4f7e-9a2b-6c1d0b5e2a01"
#: Notify-only characteristic carrying sample packets.
DATA_CHAR_UUID = "5e1fca10-0002-4f7e-9a2b-6c1d0b5e2a01"
#: Read (info record) / write (control command) characteristic.
CONTROL_CHAR_UUID = "5e1fca10-0003-4f7e-9a2b-6c1d0b5e2a01"

PACKET_VERSION = 1
INFO_VERSION = 1
#: Flag bit 0: the temperature field holds a measurement.
FLAG_TEMP_VALID = 0x01
_RESERVED_FLAGS = 0x0E

HEADER_SIZE_BYTES = 8
SAMPLE_SIZE_BYTES = 12
MAX_SAMPLES_PER_PACKET = 255
#: ATT payload of a notification at the default MTU (23 - 3).
DEFAULT_ATT_PAYLOAD_BYTES = 20

#: Accelerometer scale: counts per g (int16, ±8 g).
ACC_COUNTS_PER_G = 4096.0
#: Pressure scale: kPa per count (uint12).
PRESSURE_KPA_PER_COUNT = 0.25
PRESSURE_MAX_COUNTS = 0xFFF
#: Temperature scale: °C per count (int16).
TEMP_C_PER_COUNT = 0.01

SEQ_MODULUS = 2**32

_HEADER = struct.Struct("<BBIh")
_INFO_HEAD = struct.Struct("<BBHB")
#: The service's device ids (selfcal_service.schemas.DEVICE_ID_PATTERN): an id it would
#: refuse (or that names another path, as ``..`` does) never gets as far as the spool.
_DEVICE_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,63}$")

#: Control command: set the maximum number of samples per packet (u8 argument).
CONTROL_SET_MAX_SAMPLES = 0x01


class CodecError(SelfcalError, ValueError):
    """Base class of the codec's errors."""


class MalformedPacketError(CodecError):
    """A packet or info record that cannot be decoded; the message says why."""


@dataclass(frozen=True)
class Packet:
    """One decoded sample packet.

    Attributes
    ----------
    seq : int
        Index of the first sample since power-on (uint32, wraps).
    acc_g : ndarray, shape (n, 3), g
        Specific force, raw (uncalibrated) sensor axes.
    pressure_kpa : ndarray, shape (n, 4), kPa
        The four pressure cells.
    temp_c : float
        Temperature in °C, NaN when the packet flags it as not valid.
    """

    seq: int
    acc_g: np.ndarray
    pressure_kpa: np.ndarray
    temp_c: float

    @property
    def n(self) -> int:
        """Number of samples in the packet."""
        return int(self.acc_g.shape[0])


@dataclass(frozen=True)
class DeviceInfo:
    """The insole's info record (control/info characteristic).

    Attributes
    ----------
    device_id : str
        Stable id used in the service URL; a letter or digit, then up to 63 of ``[A-Za-z0-9._:-]`` (the service's ids).
    firmware : str
        Firmware version string (UTF-8, at most 255 bytes).
    sample_rate_hz : float
        Sample rate in Hz, resolution 0.01 Hz, 0 < rate <= 655.35.
    max_samples_per_packet : int
        The insole's current cap on samples per packet (1..255).
    packet_version : int
        Version of the sample packet format the insole sends.
    """

    device_id: str
    firmware: str
    sample_rate_hz: float
    max_samples_per_packet: int = MAX_SAMPLES_PER_PACKET
    packet_version: int = PACKET_VERSION


def samples_per_packet(att_mtu: int, cap: int = MAX_SAMPLES_PER_PACKET) -> int:
    """How many samples fit one notification at a given ATT MTU.

    Parameters
    ----------
    att_mtu : int
        Negotiated ATT MTU in bytes (>= 23); the notification payload is
        ``att_mtu - 3``.
    cap : int
        Upper bound (latency cap), 1..255.

    Returns
    -------
    int
        ``min(cap, (att_mtu - 3 - 8) // 12)``, at least 1.
    """
    if att_mtu < 23:
        raise CodecError(f"att_mtu must be >= 23 bytes, got {att_mtu}")
    if not 1 <= cap <= MAX_SAMPLES_PER_PACKET:
        raise CodecError(f"cap must be in 1..{MAX_SAMPLES_PER_PACKET}, got {cap}")
    fit = (att_mtu - 3 - HEADER_SIZE_BYTES) // SAMPLE_SIZE_BYTES
    return max(1, min(cap, fit))


def _quantize(values: np.ndarray, scale: float, lo: int, hi: int) -> np.ndarray:
    out = np.rint(np.nan_to_num(np.asarray(values, dtype=float), nan=0.0) * scale)
    return np.clip(out, lo, hi).astype(np.int64)


def encode_packet(
    seq: int,
    acc_g: np.ndarray,
    pressure_kpa: np.ndarray,
    temp_c: float | None,
) -> bytes:
    """Encode one sample packet (firmware side; used by the virtual insole).

    Values are rounded to the nearest LSB and saturated to the field range.

    Parameters
    ----------
    seq : int
        Index of the first sample; taken modulo 2**32.
    acc_g : array_like, shape (n, 3), g
        Specific force; saturates at ±8 g.
    pressure_kpa : array_like, shape (n, 4), kPa
        Pressure cells; saturate at 0 and 1023.75 kPa. NaN encodes as 0.
    temp_c : float or None
        Temperature in °C for the packet; None or NaN clears the valid flag.

    Returns
    -------
    bytes
        ``8 + 12 n`` bytes.
    """
    acc = np.asarray(acc_g, dtype=float)
    prs = np.asarray(pressure_kpa, dtype=float)
    if acc.ndim != 2 or acc.shape[1] != 3:
        raise CodecError(f"acc_g must have shape (n, 3), got {acc.shape}")
    n = acc.shape[0]
    if not 1 <= n <= MAX_SAMPLES_PER_PACKET:
        raise CodecError(f"a packet holds 1..{MAX_SAMPLES_PER_PACKET} samples, got {n}")
    if prs.shape != (n, 4):
        raise CodecError(f"pressure_kpa must have shape ({n}, 4), got {prs.shape}")
    flags = 0
    temp_counts = 0
    if temp_c is not None and np.isfinite(temp_c):
        flags |= FLAG_TEMP_VALID
        temp_counts = int(np.clip(np.rint(temp_c / TEMP_C_PER_COUNT), -32768, 32767))
    header = _HEADER.pack(
        (PACKET_VERSION << 4) | flags, n, int(seq) % SEQ_MODULUS, temp_counts
    )
    acc_counts = _quantize(acc, ACC_COUNTS_PER_G, -32768, 32767).astype("<i2")
    p = _quantize(prs, 1.0 / PRESSURE_KPA_PER_COUNT, 0, PRESSURE_MAX_COUNTS).astype(np.uint64)
    packed = p[:, 0] | (p[:, 1] << 12) | (p[:, 2] << 24) | (p[:, 3] << 36)
    p_bytes = packed.astype("<u8").view(np.uint8).reshape(n, 8)[:, :6]
    body = np.concatenate([acc_counts.view(np.uint8).reshape(n, 6), p_bytes], axis=1)
    return header + body.tobytes()


def decode_packet(data: bytes | bytearray | memoryview) -> Packet:
    """Decode one sample packet (gateway side).

    Parameters
    ----------
    data : bytes-like
        The notification payload.

    Returns
    -------
    Packet

    Raises
    ------
    MalformedPacketError
        If the length, version, reserved flag bits or sample count are wrong;
        the message names the field. No other exception is raised.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise MalformedPacketError(f"packet is not bytes-like: {type(data).__name__}")
    buf = bytes(data)
    if len(buf) < HEADER_SIZE_BYTES + SAMPLE_SIZE_BYTES:
        raise MalformedPacketError(
            f"packet length {len(buf)} bytes is shorter than the minimum "
            f"{HEADER_SIZE_BYTES + SAMPLE_SIZE_BYTES}"
        )
    vf, n, seq, temp_counts = _HEADER.unpack_from(buf)
    version, flags = vf >> 4, vf & 0x0F
    if version != PACKET_VERSION:
        raise MalformedPacketError(f"packet version {version} is not {PACKET_VERSION}")
    if flags & _RESERVED_FLAGS:
        raise MalformedPacketError(f"reserved flag bits set: 0x{flags & _RESERVED_FLAGS:x}")
    if n == 0:
        raise MalformedPacketError("sample count n is 0")
    expected = HEADER_SIZE_BYTES + SAMPLE_SIZE_BYTES * n
    if len(buf) != expected:
        raise MalformedPacketError(
            f"packet length {len(buf)} bytes does not match n={n} samples ({expected} bytes)"
        )
    body = np.frombuffer(buf, dtype=np.uint8, offset=HEADER_SIZE_BYTES).reshape(n, SAMPLE_SIZE_BYTES)
    acc_counts = body[:, :6].copy().view("<i2").reshape(n, 3)
    p8 = np.zeros((n, 8), dtype=np.uint8)
    p8[:, :6] = body[:, 6:]
    packed = p8.view("<u8").reshape(n)
    p = np.stack([(packed >> s) & PRESSURE_MAX_COUNTS for s in (0, 12, 24, 36)], axis=1)
    temp_c = temp_counts * TEMP_C_PER_COUNT if flags & FLAG_TEMP_VALID else float("nan")
    return Packet(
        seq=int(seq),
        acc_g=acc_counts.astype(float) / ACC_COUNTS_PER_G,
        pressure_kpa=p.astype(float) * PRESSURE_KPA_PER_COUNT,
        temp_c=float(temp_c),
    )


def validate_device_id(device_id: str) -> str:
    """Return ``device_id`` if it is a valid id, else raise :class:`CodecError`."""
    if not isinstance(device_id, str) or not _DEVICE_ID_RE.match(device_id):
        raise CodecError(
            f"device_id must be a letter or digit, then up to 63 of [A-Za-z0-9._:-], got {device_id!r}"
        )
    return device_id


def encode_info(info: DeviceInfo) -> bytes:
    """Encode the info record (firmware side).

    Parameters
    ----------
    info : DeviceInfo

    Returns
    -------
    bytes
    """
    validate_device_id(info.device_id)
    rate = int(round(info.sample_rate_hz * 100))
    if not 1 <= rate <= 0xFFFF:
        raise CodecError(f"sample_rate_hz must be in 0.01..655.35 Hz, got {info.sample_rate_hz}")
    if not 1 <= info.max_samples_per_packet <= MAX_SAMPLES_PER_PACKET:
        raise CodecError(
            f"max_samples_per_packet must be in 1..255, got {info.max_samples_per_packet}"
        )
    fw = info.firmware.encode("utf-8")
    if len(fw) > 255:
        raise CodecError(f"firmware string is {len(fw)} bytes, at most 255 allowed")
    dev = info.device_id.encode("ascii")
    return (
        _INFO_HEAD.pack(INFO_VERSION, info.packet_version, rate, info.max_samples_per_packet)
        + bytes([len(fw)])
        + fw
        + bytes([len(dev)])
        + dev
    )


def decode_info(data: bytes | bytearray | memoryview) -> DeviceInfo:
    """Decode the info record (gateway side).

    Raises
    ------
    MalformedPacketError
        If the record is truncated, has an unknown version, a zero sample rate,
        trailing bytes or an invalid device id.
    """
    buf = bytes(data)
    if len(buf) < _INFO_HEAD.size + 2:
        raise MalformedPacketError(f"info record of {len(buf)} bytes is truncated")
    info_version, packet_version, rate, max_n = _INFO_HEAD.unpack_from(buf)
    if info_version != INFO_VERSION:
        raise MalformedPacketError(f"info version {info_version} is not {INFO_VERSION}")
    if packet_version != PACKET_VERSION:
        raise MalformedPacketError(
            f"insole sends packet version {packet_version}; this gateway reads {PACKET_VERSION}"
        )
    if rate == 0:
        raise MalformedPacketError("info sample rate is 0 Hz")
    if max_n == 0:
        raise MalformedPacketError("info max_samples_per_packet is 0")
    pos = _INFO_HEAD.size
    fields = []
    for name in ("firmware", "device_id"):
        if pos >= len(buf):
            raise MalformedPacketError(f"info record truncated before {name}")
        length = buf[pos]
        pos += 1
        if pos + length > len(buf):
            raise MalformedPacketError(f"info {name} length {length} runs past the record")
        fields.append(buf[pos : pos + length])
        pos += length
    if pos != len(buf):
        raise MalformedPacketError(f"info record has {len(buf) - pos} trailing bytes")
    try:
        firmware = fields[0].decode("utf-8")
        device_id = validate_device_id(fields[1].decode("ascii"))
    except (UnicodeDecodeError, CodecError) as exc:
        raise MalformedPacketError(f"info record: {exc}") from exc
    return DeviceInfo(
        device_id=device_id,
        firmware=firmware,
        sample_rate_hz=rate / 100.0,
        max_samples_per_packet=max_n,
        packet_version=packet_version,
    )


def encode_control(max_samples_per_packet: int) -> bytes:
    """Control command: cap the samples per packet (trades latency for airtime).

    Parameters
    ----------
    max_samples_per_packet : int
        1..255; the insole still never exceeds what fits its MTU.
    """
    if not 1 <= max_samples_per_packet <= MAX_SAMPLES_PER_PACKET:
        raise CodecError(
            f"max_samples_per_packet must be in 1..255, got {max_samples_per_packet}"
        )
    return bytes([CONTROL_SET_MAX_SAMPLES, max_samples_per_packet])


def decode_control(data: bytes | bytearray | memoryview) -> int:
    """Decode a control command; returns the requested max samples per packet.

    Raises
    ------
    MalformedPacketError
        For an unknown opcode, a wrong length or an out-of-range value.
    """
    buf = bytes(data)
    if len(buf) != 2 or buf[0] != CONTROL_SET_MAX_SAMPLES:
        raise MalformedPacketError(f"unknown control command {buf.hex() or '(empty)'}")
    if buf[1] == 0:
        raise MalformedPacketError("control max_samples_per_packet is 0")
    return buf[1]


class SeqTracker:
    """Unwraps the uint32 sample index and detects gaps and device restarts.

    The tracker maps the insole's wrapping sample index to a monotonic sample
    count, so ``t_s = count / sample_rate_hz`` never goes backwards, even over
    a device reboot (index back to 0).

    Parameters
    ----------
    last_count : int or None
        The last unwrapped count seen (restored from the spool), or None.
    offset : int
        Offset added to the raw index (restored from the spool).

    Attributes
    ----------
    last_count : int or None
    offset : int
    """

    #: A jump forward by less than this many samples is a gap; a larger one
    #: (i.e. a jump backwards modulo 2**32) is a device restart.
    MAX_GAP = 2**31

    def __init__(self, last_count: int | None = None, offset: int = 0):
        self.last_count = last_count
        self.offset = offset

    def feed(self, seq: int, n: int) -> tuple[int, int, bool]:
        """Account for one packet.

        Parameters
        ----------
        seq : int
            Raw uint32 index of the packet's first sample.
        n : int
            Samples in the packet.

        Returns
        -------
        first_count : int
            Unwrapped count of the packet's first sample.
        lost : int
            Samples missing between the previous packet and this one.
        restarted : bool
            True if the index went backwards (BLE notifications arrive in
            order and are never repeated, so this means the insole rebooted);
            the count then continues from the last one.
        """
        if self.last_count is None:
            count = seq + self.offset
            self.last_count = count + n - 1
            return count, 0, False
        expected = self.last_count + 1
        delta = (seq - (expected - self.offset)) % SEQ_MODULUS
        if delta < self.MAX_GAP:
            count = expected + delta
            self.last_count = count + n - 1
            return count, delta, False
        self.offset = expected - seq
        self.last_count = expected + n - 1
        return expected, 0, True

"""Synthetic GENEActiv ``.bin`` files with known content, for testing the device reader path.

No real GENEActiv file is available to the project, so this writes one the way actfast
1.3.0's reader (``src/geneactiv/mod.rs`` and ``defs.rs`` in its sdist) parses it; what the
reader does is noted on each point:

* The file is text. It must start with ``Devi`` (actfast's magic for "GENEActiv BIN").
* A header of exactly 59 lines (actfast reads 59 lines, fewer is an error). A line with
  no ``:`` names a category; ``key:value`` lines belong to the last category. Used by the
  reader: "Memory Status / Number of Pages" (only to reserve memory) and "Calibration
  Data / x gain, x offset, y gain, y offset, z gain, z offset, Volts, Lux" (integers;
  ``key:`` then the value, parsed after trimming).
* Then pages of 10 lines each: 9 page-header lines ("Recorded Data", "Device Unique Serial
  Code", "Sequence Number", "Page Time", "Unassigned", "Temperature", "Battery voltage",
  "Device Status", "Measurement Frequency") and one line of hex data. Used by the reader:
  ``Page Time:%Y-%m-%d %H:%M:%S:%3f`` (read as UTC), ``Temperature`` (float, degC, one
  value per page at the page time), ``Battery voltage`` (float, V) and ``Measurement
  Frequency`` (a bare float in Hz: a unit after it would fail to parse and the reader
  would silently fall back to 1 Hz).
* The hex line: 12 hex characters (6 bytes, 48 bits, most significant bit first) per
  sample: x, y, z as 12-bit two's complement counts, light as 10 bits unsigned, the
  button as 1 bit, 1 reserved bit. The reader decodes ``len(bytes) // 6`` samples and
  drops an odd last character or a partial last sample without a word.
* Calibration: ``g = (counts * 100 - offset) / gain`` per axis (float32), light in lux
  ``= light * Lux / Volts``. Sample ``i`` of a page is at ``page_time + i *
  int(1e9 / frequency)`` ns.

Files from the devices hold 300 samples per page (the default here). Line ends are
``\\r\\n`` by default; actfast trims each line, so ``\\n`` reads the same.
"""

from __future__ import annotations

import datetime as _dt
import os
from dataclasses import dataclass

import numpy as np

#: Lines in the file header (actfast reads exactly this many before the first page).
HEADER_LINES = 59
#: Lines per page: 9 page-header lines and one hex data line.
PAGE_LINES = 10
#: Samples per page in the devices' files.
SAMPLES_PER_PAGE = 300
#: Hex characters per sample (48 bits).
HEX_PER_SAMPLE = 12
#: Plausible GENEActiv calibration block: gains (counts*100 per g) and offsets (counts*100).
DEFAULT_GAINS = (25548, 25539, 25591)
DEFAULT_OFFSETS = (-1158, -1000, -1030)
#: Light calibration (lux = light counts * LUX / VOLTS).
DEFAULT_VOLTS = 300
DEFAULT_LUX = 800
#: Default start: 2024-04-30 15:13:30 UTC (unix seconds).
DEFAULT_START_UNIX_S = 1_714_490_010.0

_TIME_FORMAT = "%Y-%m-%d %H:%M:%S"


@dataclass
class GeneactivContent:
    """What a reader should get back from a file written by :func:`write_geneactiv_bin`.

    ``counts`` (n, 3) int16: the 12-bit counts written; ``acc_g`` (n, 3) float64: the
    counts calibrated back to g exactly as the reader does (the quantised input);
    ``page_t_s`` (n_pages,) float64: each page's time in s after the start (ms-rounded as
    written); ``temp_c`` (n_pages,) float64: the temperatures as written (rounded to
    0.01 degC); ``start_unix_s``: the first page time, unix s (UTC, ms-rounded);
    ``rate_hz``: sample rate; ``quant_g`` (3,): one count in g per axis.
    """

    path: str
    counts: np.ndarray
    acc_g: np.ndarray
    page_t_s: np.ndarray
    temp_c: np.ndarray
    start_unix_s: float
    rate_hz: float
    quant_g: np.ndarray


def _stamp(unix_s: float) -> str:
    """``YYYY-MM-DD hh:mm:ss:mmm`` (UTC) of a unix time in s, rounded to the ms."""
    ms = int(round(unix_s * 1000.0))
    t = _dt.datetime.fromtimestamp(ms // 1000, tz=_dt.timezone.utc)
    return f"{t.strftime(_TIME_FORMAT)}:{ms % 1000:03d}"


def _freq(rate_hz: float) -> str:
    """The rate as the page header writes it (``100.0``; more digits when needed)."""
    r = float(rate_hz)
    return f"{r:.1f}" if abs(r * 10 - round(r * 10)) < 1e-9 else f"{r:.6g}"


def counts_from_g(acc_g: np.ndarray, gains=DEFAULT_GAINS, offsets=DEFAULT_OFFSETS) -> np.ndarray:
    """12-bit counts (n, 3) int16 whose calibration gives ``acc_g`` (n, 3, g) to within half a count.

    Inverse of the reader's ``g = (counts * 100 - offset) / gain``; clipped to the 12-bit
    range [-2048, 2047] (about +-8 g with the default gains).
    """
    gain = np.asarray(gains, dtype=np.float64)
    off = np.asarray(offsets, dtype=np.float64)
    c = np.rint((np.asarray(acc_g, dtype=np.float64) * gain + off) / 100.0)
    return np.clip(c, -2048, 2047).astype(np.int16)


def g_from_counts(counts: np.ndarray, gains=DEFAULT_GAINS, offsets=DEFAULT_OFFSETS) -> np.ndarray:
    """Acceleration (n, 3) in g from counts (n, 3), as the reader computes it (float32 math)."""
    gain = np.asarray(gains, dtype=np.float32)
    off = np.asarray(offsets, dtype=np.float32)
    return ((np.asarray(counts).astype(np.float32) * np.float32(100.0) - off) / gain).astype(np.float64)


def pack_hex(counts: np.ndarray, light: np.ndarray | None = None, button: np.ndarray | None = None) -> str:
    """The hex text (12 upper-case characters per sample) of counts (n, 3) int, light (n,) 0..1023, button (n,) bool.

    Bit layout per sample, most significant first: x 12, y 12, z 12 (two's complement),
    light 10, button 1, reserved 1 (0).
    """
    c = np.asarray(counts, dtype=np.int64)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"counts must be (n, 3), got {c.shape}")
    if np.any(c < -2048) or np.any(c > 2047):
        raise ValueError("counts must fit 12-bit two's complement (-2048..2047)")
    n = len(c)
    lt = np.zeros(n, np.int64) if light is None else np.asarray(light, dtype=np.int64)
    if np.any(lt < 0) or np.any(lt > 1023):
        raise ValueError("light counts must be 0..1023 (10 bits)")
    bt = np.zeros(n, np.int64) if button is None else np.asarray(button, dtype=bool).astype(np.int64)
    u = c & 0xFFF  # two's complement in 12 bits
    word = (u[:, 0] << 36) | (u[:, 1] << 24) | (u[:, 2] << 12) | (lt << 2) | (bt << 1)
    six = word.astype(">u8").view(np.uint8).reshape(n, 8)[:, 2:]  # the low 48 bits, big-endian
    return six.tobytes().hex().upper()


def _header(*, serial: str, rate_hz: float, start_unix_s: float, n_pages: int, gains, offsets,
            volts: int, lux: int) -> list[str]:
    """The 59 header lines (no line ends)."""
    lines = [
        "Device Identity",
        f"Device Unique Serial Code:{serial}",
        "Device Type:GENEActiv",
        "Device Model:1.1",
        "Device Firmware Version:Ver06.17 15June2015",
        "Calibration Date:2024-01-01 00:00:00:000",
        "",
        "Device Capabilities",
        "Accelerometer Range:-8 to 8",
        "Accelerometer Resolution:0.0039",
        "Accelerometer Units:g",
        "Light Meter Range:0 to 5000",
        "Light Meter Resolution:5",
        "Light Meter Units:lux",
        "Temperature Sensor Range:0 to 60",
        "Temperature Sensor Resolution:0.25",
        "Temperature Sensor Units:deg. C",
        "",
        "Configuration Info",
        f"Measurement Frequency:{_freq(rate_hz)} Hz",
        "Measurement Period:168 Hours",
        f"Start Time:{_stamp(start_unix_s)}",
        "Time Zone:GMT +00:00",
        "",
        "Trial Info",
        "Study Centre:selfcal",
        "Study Code:synthetic",
        "Investigator ID:",
        "Exercise Type:",
        "Config Operator ID:",
        f"Config Time:{_stamp(start_unix_s - 60.0)}",
        "Config Notes:synthetic file written by tests/geneactivgen.py, not recorded by a device",
        "Extract Operator ID:",
        f"Extract Time:{_stamp(start_unix_s + n_pages * 3600.0)}",
        "Extract Notes:",
        "",
        "Subject Info",
        "Device Location Code:left wrist",
        "Subject Code:",
        "Date of Birth:",
        "Sex:",
        "Height:",
        "Weight:",
        "Handedness Code:",
        "Subject Notes:",
        "",
        "Calibration Data",
        f"x gain:{int(gains[0])}",
        f"x offset:{int(offsets[0])}",
        f"y gain:{int(gains[1])}",
        f"y offset:{int(offsets[1])}",
        f"z gain:{int(gains[2])}",
        f"z offset:{int(offsets[2])}",
        f"Volts:{int(volts)}",
        f"Lux:{int(lux)}",
        "",
        "Memory Status",
        f"Number of Pages:{n_pages}",
        "",
    ]
    assert len(lines) == HEADER_LINES, len(lines)
    return lines


def write_geneactiv_bin(path: str | os.PathLike, acc_g: np.ndarray, rate_hz: float, temp_c=25.0, *,
                        start_unix_s: float = DEFAULT_START_UNIX_S, gains=DEFAULT_GAINS, offsets=DEFAULT_OFFSETS,
                        volts: int = DEFAULT_VOLTS, lux: int = DEFAULT_LUX, light=None, button=None,
                        battery_v=4.0, samples_per_page: int = SAMPLES_PER_PAGE, serial: str = "SYN000001",
                        newline: str = "\r\n") -> GeneactivContent:
    """Write a GENEActiv ``.bin`` holding ``acc_g`` and return what a reader should decode.

    Parameters
    ----------
    path : where to write (overwritten).
    acc_g : (n, 3) acceleration in g; ``n`` must be a whole number of pages
        (``samples_per_page``, 300 like the devices) - a shorter last page would look cut.
        Quantised to 12-bit counts with ``gains``/``offsets`` (~3.9 mg a count).
    rate_hz : sample rate in Hz (GENEActiv: 10..100); pages follow each other without gaps.
    temp_c : temperature in degC, one per page (n_pages,) or a scalar; written to 0.01 degC.
    start_unix_s : time of the first sample, unix s (UTC); written to the ms.
    gains, offsets : the header's calibration block, 3 integers each (counts*100 per g,
        counts*100).
    volts, lux : the light calibration (lux = counts * lux / volts).
    light : (n,) light counts 0..1023 or None (0); button : (n,) bool or None (False).
    battery_v : battery voltage in V, per page (n_pages,) or a scalar.
    samples_per_page : samples in each page's hex line.
    serial : device serial written in the header and each page.
    newline : line end (``"\\r\\n"`` or ``"\\n"``).

    Returns
    -------
    GeneactivContent with the quantised acceleration in g, page times and temperatures.
    """
    acc = np.asarray(acc_g, dtype=np.float64)
    if acc.ndim != 2 or acc.shape[1] != 3 or len(acc) == 0:
        raise ValueError(f"acc_g must be (n, 3) with n > 0, got {acc.shape}")
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
    n = len(acc)
    if n % samples_per_page:
        raise ValueError(f"{n} samples is not a whole number of {samples_per_page}-sample pages")
    n_pages = n // samples_per_page
    temps = np.broadcast_to(np.asarray(temp_c, dtype=np.float64), (n_pages,))
    batt = np.broadcast_to(np.asarray(battery_v, dtype=np.float64), (n_pages,))
    counts = counts_from_g(acc, gains, offsets)
    hexes = pack_hex(counts, light, button)
    per = samples_per_page * HEX_PER_SAMPLE
    page_unix = start_unix_s + np.arange(n_pages) * (samples_per_page / float(rate_hz))
    page_unix = np.round(page_unix * 1000.0) / 1000.0  # what the ms-resolution stamps say
    lines = _header(serial=serial, rate_hz=rate_hz, start_unix_s=float(page_unix[0]), n_pages=n_pages,
                    gains=gains, offsets=offsets, volts=volts, lux=lux)
    freq = _freq(rate_hz)
    for k in range(n_pages):
        lines += [
            "Recorded Data",
            f"Device Unique Serial Code:{serial}",
            f"Sequence Number:{k}",
            f"Page Time:{_stamp(page_unix[k])}",
            "Unassigned:",
            f"Temperature:{temps[k]:.2f}",
            f"Battery voltage:{batt[k]:.2f}",
            "Device Status:Recording",
            f"Measurement Frequency:{freq}",
            hexes[k * per:(k + 1) * per],
        ]
    with open(path, "w", encoding="ascii", newline="") as fh:
        fh.write(newline.join(lines) + newline)
    return GeneactivContent(
        path=os.fspath(path), counts=counts, acc_g=g_from_counts(counts, gains, offsets),
        page_t_s=page_unix - page_unix[0], temp_c=np.round(temps, 2), start_unix_s=float(page_unix[0]),
        rate_hz=float(rate_hz), quant_g=100.0 / np.asarray(gains, dtype=np.float64))


#: The committed fixture's recipe (data/device-formats/PROVENANCE.txt describes it).
FIXTURE_SEED = 20240430
FIXTURE_RATE_HZ = 10.0
FIXTURE_PAGES = 4


def fixture_signal(seed: int = FIXTURE_SEED, rate_hz: float = FIXTURE_RATE_HZ, pages: int = FIXTURE_PAGES):
    """The committed fixture's content: (acc_g (n, 3), temp_c (pages,)).

    Eight still orientations (the six faces tilted a few degrees, two diagonals) of equal
    length, each ending in a 2 s smooth turn to the next; a sensor error of offsets
    (+25, -15, +30) mg and scales (1.010, 0.992, 1.005) on gravity; white noise 2.5 mg per
    axis; temperature rising linearly 22 -> 25.5 degC over the pages.
    """
    rng = np.random.default_rng(seed)
    n = pages * SAMPLES_PER_PAGE
    dirs = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0],
                     [1, 1, 1], [-1, 1, -1]], dtype=np.float64)
    dirs = dirs + rng.normal(0.0, np.deg2rad(3.0), dirs.shape)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    seg = n // len(dirs)
    turn = int(round(2.0 * rate_hz))
    k = np.minimum(np.arange(n) // seg, len(dirs) - 1)
    pos = np.arange(n) - k * seg
    nxt = np.minimum(k + 1, len(dirs) - 1)
    w = np.clip((pos - (seg - turn)) / turn, 0.0, 1.0)
    w = 0.5 - 0.5 * np.cos(np.pi * w)  # smooth turn in the last `turn` samples of a pose
    g = (1 - w)[:, None] * dirs[k] + w[:, None] * dirs[nxt]
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    offset = np.array([0.025, -0.015, 0.030])
    scale = np.array([1.010, 0.992, 1.005])
    acc = g * scale + offset + rng.normal(0.0, 0.0025, (n, 3))
    temp = np.linspace(22.0, 25.5, pages)
    return acc, temp


def write_fixture(path: str | os.PathLike) -> GeneactivContent:
    """Write the committed fixture ``data/device-formats/geneactiv_synthetic.bin`` to ``path``."""
    acc, temp = fixture_signal()
    return write_geneactiv_bin(path, acc, FIXTURE_RATE_HZ, temp)


if __name__ == "__main__":  # python tests/geneactivgen.py data/device-formats/geneactiv_synthetic.bin
    import sys

    out = sys.argv[1] if len(sys.argv) > 1 else "geneactiv_synthetic.bin"
    c = write_fixture(out)
    print(f"{out}: {len(c.counts)} samples, {len(c.page_t_s)} pages, {os.path.getsize(out)} bytes")

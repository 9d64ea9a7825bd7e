"""Device formats: Axivity ``.cwa``, ActiGraph ``.gt3x`` and GENEActiv ``.bin`` through ``actfast``.

``actfast`` (MIT, extra ``formats``) decodes a whole file at once into float32 arrays in
g; nothing here copies them again. A file becomes a ``kind=samples`` recording in g:

* ``t_s``: seconds since the first sample (float64); the absolute start is kept in
  ``meta['start_unix_s']``.
* ``acc``: the device's acceleration (g, the device's own scaling; float32, as decoded).
* ``temp_c``: the device temperature, interpolated from its own (~1 Hz) time base to
  every sample (float32), when the format has one (Axivity, GENEActiv).

Peak memory is about 12 bytes per sample for acceleration and 4 for temperature plus
8 for time: ~200 MB per day of 100 Hz data (README).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from selfcal.errors import InputError

#: Suffix -> format name, for the formats actfast decodes (the reader's own table).
from selfcal.io import BINARY_DEVICE_SUFFIXES as DEVICE_SUFFIXES  # noqa: E402


def is_device_file(path: str | os.PathLike) -> bool:
    """True for a suffix this module reads (``.cwa``, ``.gt3x``, ``.bin``)."""
    return Path(path).suffix.lower() in DEVICE_SUFFIXES


def _series(ts: dict, name: str):
    """The (datetime ns, values) pair of the first time series that carries ``name``."""
    for group in ts.values():
        if isinstance(group, dict) and name in group:
            return np.asarray(group["datetime"]), group[name]
    return None, None


#: Axivity files are whole 512-byte sectors (a 1024-byte header, then data blocks).
CWA_SECTOR_BYTES = 512

#: GENEActiv ``.bin`` files are text: a 59-line header, then pages of 10 lines (9 page-header
#: lines, then one line of hex data, 12 hex characters a sample, 300 samples a page).
BIN_HEADER_LINES = 59
BIN_PAGE_LINES = 10
BIN_HEX_PER_SAMPLE = 12
#: Longest line read while checking a ``.bin`` (a page's hex line is 3600 characters).
_BIN_MAX_LINE = 1 << 16
_HEX_LINE = re.compile(rb"[0-9A-Fa-f]+")


def _check_bin_not_cut(path: Path, fmt: str) -> None:
    """Refuse a GENEActiv ``.bin`` whose last page is cut (reads its first page and its tail only).

    actfast 1.3 refuses a file cut inside the header or inside a page's 9 header lines,
    but a cut inside the last page's hex line silently loses the rest of that page (it
    decodes ``len // 12`` samples). The last line must be a hex line as long as the first
    page's (every page holds the same number of samples). A file cut exactly at a page
    boundary still reads as a shorter recording, as a ``.cwa`` cut at a sector boundary does.
    """
    with open(path, "rb") as fh:
        if fh.read(4) != b"Devi":  # not actfast's GENEActiv magic ("Device Identity"): it says what it is
            return
        fh.seek(0)
        for _ in range(BIN_HEADER_LINES + BIN_PAGE_LINES):
            line = fh.readline(_BIN_MAX_LINE)
            if not line:
                return  # no whole first page: actfast refuses it or it holds no samples
        first = line.strip()
        if not _HEX_LINE.fullmatch(first):
            return  # not the layout checked here: actfast decides
        size = fh.seek(0, os.SEEK_END)
        fh.seek(max(0, size - len(first) - 256))
        last = fh.read().rstrip().rsplit(b"\n", 1)[-1].strip()
    if not _HEX_LINE.fullmatch(last):
        shown = last[:40].decode("ascii", "replace")
        raise InputError(f"{path}: truncated {fmt} file: it ends inside a page header (last line {shown!r}); "
                         "copy the file again")
    if len(last) % BIN_HEX_PER_SAMPLE:
        raise InputError(
            f"{path}: truncated {fmt} file: the last page's data line has {len(last)} hex characters, not a "
            f"whole number of {BIN_HEX_PER_SAMPLE}-character samples (the page is cut); copy the file again")
    if len(last) != len(first):
        raise InputError(
            f"{path}: truncated {fmt} file: the last page's data line holds {len(last) // BIN_HEX_PER_SAMPLE} "
            f"samples where the first page's holds {len(first) // BIN_HEX_PER_SAMPLE} (the page is cut); "
            "copy the file again")


def _check_not_cut(path: Path, fmt: str) -> None:
    """Refuse a file whose size shows it was cut (a copy or download that stopped).

    An Axivity ``.cwa`` is a whole number of 512-byte sectors; actfast silently drops a
    partial last sector, so a cut copy would otherwise calibrate as a shorter recording.
    A GENEActiv ``.bin`` whose last page is cut would lose that page's rest the same way
    (:func:`_check_bin_not_cut`). (A cut ``.gt3x`` is a broken zip archive, which actfast
    already refuses.)
    """
    if path.suffix.lower() == ".bin":
        _check_bin_not_cut(path, fmt)
    if path.suffix.lower() == ".cwa":
        with open(path, "rb") as fh:
            if fh.read(2) != b"MD":  # not an Axivity file at all (garbage, another format)
                raise InputError(f"{path}: cannot decode as {fmt}: it does not start with the 'MD' header block")
        size = path.stat().st_size
        if size % CWA_SECTOR_BYTES:
            raise InputError(
                f"{path}: truncated {fmt} file: {size} bytes is not a whole number of {CWA_SECTOR_BYTES}-byte "
                f"sectors (the last {size % CWA_SECTOR_BYTES} bytes are a cut sector); copy the file again")


def read_device(path: str | os.PathLike):
    """Decode a device file into a :class:`selfcal.io.Recording` (``kind=samples``, unit g).

    Raises InputError naming the file when ``actfast`` is missing or the file is corrupt.
    """
    from selfcal.io import Recording

    name = os.fspath(path)
    fmt = DEVICE_SUFFIXES.get(Path(path).suffix.lower(), "device")
    if not Path(path).is_file():
        raise InputError(f"{name}: no such file")
    _check_not_cut(Path(path), fmt)
    try:
        import actfast
    except ImportError:
        raise InputError(f"{name}: reading {fmt} files needs the 'formats' extra (pip install 'selfcal[formats]')") from None
    try:
        data = actfast.read(name)
    except Exception as exc:  # noqa: BLE001 - actfast raises plain errors on corrupt input
        raise InputError(f"{name}: cannot decode as {fmt}: {exc}") from None
    ts = data.get("timeseries", {})
    dt_ns, acc = _series(ts, "acceleration")
    if acc is None or len(acc) == 0:
        raise InputError(f"{name}: the {fmt} file holds no acceleration samples")
    acc = np.asarray(acc)
    if acc.dtype != np.float32:
        acc = acc.astype(np.float32)
    t0 = int(dt_ns[0])
    t_s = (dt_ns - t0).astype(np.float64) * 1e-9
    order_ok = bool(np.all(np.diff(t_s) >= 0))
    if not order_ok:
        raise InputError(f"{name}: sample times go backwards in the {fmt} file")
    temp = None
    tdt, tval = _series(ts, "temperature")
    if tval is not None and len(tval):
        tt = (np.asarray(tdt) - t0).astype(np.float64) * 1e-9
        temp = np.interp(t_s, tt, np.asarray(tval, dtype=np.float64)).astype(np.float32)
    meta = {"format": str(data.get("format", fmt)), "start_unix_s": f"{t0 * 1e-9:.6f}", "dropped_rows": "0",
            "source": Path(path).name}
    return Recording(kind="samples", unit="g", t_s=t_s, acc=acc, temp_c=temp, meta=meta, path=name)

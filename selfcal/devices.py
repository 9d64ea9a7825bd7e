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


def _check_not_cut(path: Path, fmt: str) -> None:
    """Refuse a file whose size shows it was cut (a copy or download that stopped).

    An Axivity ``.cwa`` is a whole number of 512-byte sectors; actfast silently drops a
    partial last sector, so a cut copy would otherwise calibrate as a shorter recording.
    (A cut ``.gt3x`` is a broken zip archive, which actfast already refuses.)
    """
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

"""Recording files: the CSV contract of ``docs/design.md`` ("Recording files").

A recording is UTF-8 text::

    # selfcal-recording v1
    # kind=samples
    # sensor=Moticon OpenGo insole        <- '# key=value' lines before the header -> meta
    # free text comments are ignored
    t_s,ax_g,ay_g,az_g,temp_c,p1_ncm2,p2_ncm2
    0.00,0.01,-0.02,0.99,24.5,1.25,0.5
    ...

:func:`read_recording` parses it into a :class:`Recording`; :func:`write_recording`
writes one back (exact round trip of every float, shortest ``repr`` text).

Reader behaviour
----------------
* The first comment line must be ``# selfcal-recording v1`` and a ``# kind=samples``
  or ``# kind=poses`` line must come before the header row. Other ``# key=value``
  lines before the header go to ``meta`` (strings); any other comment, and every
  comment after the header, is ignored. Blank lines are ignored.
* The acceleration unit is read from the column names (``ax_g``/``ax_mps2``/
  ``ax_counts``; all three axes must agree). Pressure columns ``p<i>_<unit>`` are
  ordered by ``i`` and must share one unit. A poses table needs ``sd[xyz]_<unit>``
  (same unit as the acceleration) and ``duration_s``; ``n`` is optional. Every other
  column is kept in ``extra`` (numeric columns as float64, non-numeric as ``str``).
* Missing data: a row with a **blank** cell in ``t_s`` or an acceleration column (or,
  in a poses table, an ``sd`` column) is dropped; the number of dropped rows is put
  in ``meta['dropped_rows']`` (always present, ``"0"`` when none). Blank cells in
  any other column become NaN. ``NaN``/``inf`` *written as text* in ``t_s``,
  acceleration or ``sd`` is an error, not missing data.
* Every problem raises :class:`selfcal.errors.InputError` with a message
  ``path:LINE:COL: reason``: LINE is the 1-based line in the file, COL the 1-based
  column number, and the reason names the column (``column 3 'ay_g'``). Problems
  that are not about one column (magic line, kind, empty table) use COL 1.

Performance: the table is parsed as one string split plus one vectorised
string-to-float conversion (about 0.1 s for 58 000 rows x 5 columns); a slower
column-by-column path runs only when a cell is blank or non-numeric, and a per-cell
Python loop runs only to locate the exact cell of an error.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import itertools
import os
import re
import secrets
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from selfcal import STANDARD_GRAVITY_MPS2
from selfcal.errors import InputError

__all__ = [
    "ACC_UNITS",
    "KINDS",
    "PRESSURE_TO_KPA",
    "Recording",
    "read_recording",
    "write_recording",
]

#: Acceleration units a recording may use (the suffix of ``ax_<unit>``).
ACC_UNITS = ("g", "mps2", "counts")
#: Table kinds (``# kind=<kind>``).
KINDS = ("samples", "poses")
#: Pressure units with a known factor to kPa (``p<i>_<unit>``).
PRESSURE_TO_KPA = {"ncm2": 10.0, "kpa": 1.0}
#: Factor from an acceleration unit to g (``counts`` has no known factor).
ACC_TO_G = {"g": 1.0, "mps2": 1.0 / STANDARD_GRAVITY_MPS2}

MAGIC_LINE = "# selfcal-recording v1"
_MAGIC_RE = re.compile(r"^#\s*selfcal-recording\s+(\S+)\s*$")
_META_RE = re.compile(r"^#\s*([A-Za-z_][A-Za-z0-9_.\-]*)\s*=(.*)$")
_ACC_RE = re.compile(r"^a([xyz])_([A-Za-z0-9]+)$")
_SD_RE = re.compile(r"^sd([xyz])_([A-Za-z0-9]+)$")
_P_RE = re.compile(r"^p([0-9]+)_([A-Za-z0-9]+)$")
_UNIT_RE = re.compile(r"^[A-Za-z0-9]+$")
_GYRO_COLUMNS = ("gx_dps", "gy_dps", "gz_dps")
_AXES = "xyz"
#: meta keys the reader derives itself; the writer does not write them.
_DERIVED_META = ("dropped_rows",)


@dataclass(eq=False)
class Recording:
    """One recording: a raw sample stream or a table of still windows (poses).

    Parameters
    ----------
    kind : {"samples", "poses"}
        Table kind.
    unit : {"g", "mps2", "counts"}
        Unit of ``acc`` (and ``sd``).
    t_s : ndarray, shape (n,), s
        Sample (or window) times, non-decreasing.
    acc : ndarray, shape (n, 3), `unit`
        Specific force per axis (poses: window mean).
    temp_c : ndarray, shape (n,), degC, or None
        Sensor temperature; NaN where the file had a blank cell.
    pressure : ndarray, shape (n, k), `pressure_unit`, or None
        Pressure cells ``p1..pk`` in index order; NaN where blank.
    pressure_unit : str or None
        Unit suffix of the pressure columns, e.g. ``"ncm2"`` or ``"kpa"``.
    gyro_dps : ndarray, shape (n, 3), deg/s, or None
        Angular rate; NaN where blank.
    sd : ndarray, shape (n, 3), `unit`, or None
        Poses only: per-axis standard deviation within the window.
    duration_s : ndarray, shape (n,), s, or None
        Poses only: window duration.
    n : ndarray of int64, shape (n,), or None
        Poses only: samples per window, if the file gives them.
    extra : dict of str to ndarray, shape (n,)
        Unknown columns by name (float64, or ``str`` if not numeric).
    meta : dict of str to str
        ``# key=value`` comment lines before the header; the reader adds
        ``meta['dropped_rows']`` (rows dropped for blank time/acceleration cells).
    path : str or None
        File the recording was read from.
    """

    kind: str
    unit: str
    t_s: np.ndarray
    acc: np.ndarray
    temp_c: np.ndarray | None = None
    pressure: np.ndarray | None = None
    pressure_unit: str | None = None
    gyro_dps: np.ndarray | None = None
    sd: np.ndarray | None = None
    duration_s: np.ndarray | None = None
    n: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, str] = field(default_factory=dict)
    path: str | None = None

    def __post_init__(self) -> None:
        _check_fields(self)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def acc_g(self) -> np.ndarray:
        """Acceleration in g.

        Returns
        -------
        acc_g : ndarray, shape (n, 3), g
            A new array (``mps2`` divided by standard gravity 9.80665 m/s^2).

        Raises
        ------
        InputError
            If the unit is ``counts`` (the scale is unknown until calibrated).
        """
        return self.acc * self._g_factor("acc")

    def sd_g(self) -> np.ndarray:
        """Per-window standard deviation in g (poses tables).

        Returns
        -------
        sd_g : ndarray, shape (n, 3), g

        Raises
        ------
        InputError
            If the recording has no ``sd`` (not a poses table) or is in counts.
        """
        if self.sd is None:
            raise InputError(f"{self._name()}: no sd columns (kind={self.kind!r}, not a poses table)")
        return self.sd * self._g_factor("sd")

    def pressure_kpa(self) -> np.ndarray | None:
        """Pressure cells in kPa (1 N/cm^2 = 10 kPa).

        Returns
        -------
        pressure_kpa : ndarray, shape (n, k), kPa, or None
            None if the recording has no pressure columns.

        Raises
        ------
        InputError
            If the pressure unit has no known factor to kPa (see ``PRESSURE_TO_KPA``).
        """
        if self.pressure is None:
            return None
        factor = PRESSURE_TO_KPA.get(str(self.pressure_unit))
        if factor is None:
            raise InputError(
                f"{self._name()}: pressure unit {self.pressure_unit!r} has no known factor to kPa "
                f"(known: {', '.join(PRESSURE_TO_KPA)})"
            )
        return self.pressure * factor

    def rate_hz(self) -> float:
        """Median sample rate of a samples table.

        Returns
        -------
        rate_hz : float, Hz
            ``1 / median(dt)`` over the positive time steps (gaps and repeated
            time stamps do not bias it).

        Raises
        ------
        InputError
            If the table is a poses table or has fewer than two distinct times.
        """
        if self.kind != "samples":
            raise InputError(f"{self._name()}: rate_hz needs kind='samples', this is kind={self.kind!r}")
        dt_s = np.diff(self.t_s)
        dt_s = dt_s[dt_s > 0]
        if dt_s.size == 0:
            raise InputError(f"{self._name()}: rate_hz needs at least two distinct t_s values")
        return float(1.0 / np.median(dt_s))

    def _g_factor(self, what: str) -> float:
        factor = ACC_TO_G.get(self.unit)
        if factor is None:
            raise InputError(
                f"{self._name()}: {what} is in {self.unit!r}: the scale to g is unknown "
                "(raw counts need a calibration first)"
            )
        return factor

    def _name(self) -> str:
        return self.path if self.path is not None else "<recording>"


#: What a reader accepts, for the error that meets anything else.
_ACCEPTED = ("accepted: a selfcal recording CSV ('# selfcal-recording v1' header, units in every column name), "
             "or an Axivity .cwa, ActiGraph .gt3x or GENEActiv .bin file")

#: Device formats recognised by their suffix (decoded by ``selfcal.devices`` through actfast).
BINARY_DEVICE_SUFFIXES = {".cwa": "Axivity CWA", ".gt3x": "ActiGraph GT3X", ".bin": "GENEActiv BIN"}

_EXAMPLE = ("; a recording starts with the lines '# selfcal-recording v1' and '# kind=samples' (or "
            "'# kind=poses') above a header with the unit in every name, e.g. 't_s,ax_g,ay_g,az_g,temp_c'")

def _check_fields(rec: Recording) -> None:
    """Check kinds, units and shapes of a Recording; raise InputError naming the field."""
    where = rec.path if rec.path is not None else "Recording"
    if rec.kind not in KINDS:
        raise InputError(f"{where}: kind must be one of {KINDS}, got {rec.kind!r}")
    if rec.unit not in ACC_UNITS:
        raise InputError(f"{where}: unit must be one of {ACC_UNITS}, got {rec.unit!r}")
    rec.t_s = np.asarray(rec.t_s, dtype=np.float64)
    if rec.t_s.ndim != 1:
        raise InputError(f"{where}: t_s must have shape (n,), got {rec.t_s.shape}")
    n_rows = rec.t_s.shape[0]
    # float32 stays float32 (device files decode to it; half the memory), anything else float64
    rec.acc = np.asarray(rec.acc, dtype=np.float32 if np.asarray(rec.acc).dtype == np.float32 else np.float64)
    shapes = {"acc": (rec.acc, (n_rows, 3))}
    if rec.n is not None:
        n_raw = np.asarray(rec.n)
        if n_raw.dtype.kind not in "iu" and not (
            n_raw.dtype.kind in "fb" and np.all(np.isfinite(n_raw)) and np.all(n_raw == np.round(n_raw))
        ):
            raise InputError(f"{where}: n (samples per window) must hold whole numbers, got dtype {n_raw.dtype}")
    for name in ("temp_c", "duration_s", "n"):
        value = getattr(rec, name)
        if value is not None:
            keep32 = name == "temp_c" and np.asarray(value).dtype == np.float32
            value = np.asarray(value, dtype=np.int64 if name == "n" else (np.float32 if keep32 else np.float64))
            setattr(rec, name, value)
            shapes[name] = (value, (n_rows,))
    for name in ("gyro_dps", "sd"):
        value = getattr(rec, name)
        if value is not None:
            value = np.asarray(value, dtype=np.float64)
            setattr(rec, name, value)
            shapes[name] = (value, (n_rows, 3))
    if rec.pressure is not None:
        rec.pressure = np.asarray(rec.pressure, dtype=np.float64)
        if rec.pressure.ndim != 2:
            raise InputError(f"{where}: pressure must have shape (n, k), got {rec.pressure.shape}")
        shapes["pressure"] = (rec.pressure, (n_rows, rec.pressure.shape[1]))
        if not rec.pressure_unit or not _UNIT_RE.match(rec.pressure_unit):
            raise InputError(f"{where}: pressure_unit must be a unit suffix like 'ncm2', got {rec.pressure_unit!r}")
    for name, (value, shape) in shapes.items():
        if value.shape != shape:
            raise InputError(f"{where}: {name} must have shape {shape} to match t_s, got {value.shape}")
    for name, value in rec.extra.items():
        if np.shape(value) != (n_rows,):
            raise InputError(f"{where}: extra[{name!r}] must have shape ({n_rows},), got {np.shape(value)}")
    if rec.kind == "poses" and (rec.sd is None or rec.duration_s is None):
        raise InputError(f"{where}: a poses recording needs sd (n, 3) and duration_s (n,)")


# --------------------------------------------------------------------------- reading


#: The longest line of a recording's preamble (and a plain CSV's first line), bytes: a file
#: without line ends is refused at this length, not read whole into one line.
_MAX_HEAD_LINE = 1 << 20


def _error(path: str, line: int, col: int, reason: str) -> InputError:
    return InputError(f"{path}:{line}:{col}: {reason}")


def _col(names: list[str], j: int) -> str:
    return f"column {j + 1} {names[j]!r}"


@dataclass
class _Layout:
    """Where each field lives in the header (0-based column indices)."""

    t: int
    acc: list[int]
    unit: str
    sd: list[int] | None
    duration: int | None
    n: int | None
    temp: int | None
    gyro: list[int] | None
    pressure: list[int]
    pressure_unit: str | None
    extra: list[int]

    def required(self) -> list[int]:
        """Columns where a blank cell drops the row and NaN/inf text is an error."""
        return [self.t, *self.acc, *(self.sd or [])]


def _parse_preamble(path: str, lines: list[str]) -> tuple[int, str, dict[str, str]]:
    """Find the header row; return (header index, kind, meta)."""
    meta: dict[str, str] = {}
    kind: str | None = None
    kind_line = 0
    magic_seen = False
    for i, line in enumerate(lines):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            if not magic_seen:
                m = _MAGIC_RE.match(s)
                if m is None:
                    shown = s if len(s) <= 80 else s[:80] + "..."
                    raise _error(path, i + 1, 1, f"first comment line must be {MAGIC_LINE!r}, got {shown!r}")
                if m.group(1) != "v1":
                    raise _error(path, i + 1, 1, f"unsupported recording version {m.group(1)!r} (this reader knows v1)")
                magic_seen = True
                continue
            m = _META_RE.match(s)
            if m is None:
                continue
            key, value = m.group(1), m.group(2).strip()
            if key == "kind":
                if value not in KINDS:
                    raise _error(path, i + 1, 1, f"unknown kind {value!r} (expected 'samples' or 'poses')")
                if kind is not None and value != kind:
                    raise _error(path, i + 1, 1, f"kind={value} contradicts kind={kind} on line {kind_line}")
                kind, kind_line = value, i + 1
            else:
                meta[key] = value
            continue
        if not magic_seen:
            raise _error(path, i + 1, 1, f"missing magic line {MAGIC_LINE!r} before the header row{_EXAMPLE}")
        if kind is None:
            raise _error(path, i + 1, 1, "missing '# kind=samples' or '# kind=poses' line before the header row")
        return i, kind, meta
    if not magic_seen:
        raise _error(path, 1, 1, f"missing magic line {MAGIC_LINE!r} (file has no comment line){_EXAMPLE}")
    raise _error(path, len(lines), 1, "no header row (file has only comments)")


def _parse_header(path: str, line_no: int, names: list[str], kind: str) -> _Layout:
    """Map the header's column names to fields; validate units and required columns."""
    err = lambda j, reason: _error(path, line_no, j + 1, f"{_col(names, j)}: {reason}")  # noqa: E731
    seen: dict[str, int] = {}
    for j, name in enumerate(names):
        if not name:
            raise _error(path, line_no, j + 1, f"column {j + 1} has an empty name")
        if name in seen:
            raise err(j, f"duplicate column name (also column {seen[name] + 1})")
        seen[name] = j

    acc: dict[str, tuple[int, str]] = {}
    sd: dict[str, tuple[int, str]] = {}
    pressure: list[tuple[int, int, str]] = []
    extra: list[int] = []
    for j, name in enumerate(names):
        if m := _ACC_RE.match(name):
            axis, unit = m.groups()
            if unit not in ACC_UNITS:
                raise err(j, f"unknown acceleration unit {unit!r} (expected one of {', '.join(ACC_UNITS)})")
            if axis in acc:
                other = acc[axis][0]
                raise err(j, f"second a{axis} column (also {_col(names, other)})")
            acc[axis] = (j, unit)
        elif kind == "poses" and (m := _SD_RE.match(name)):
            axis, unit = m.groups()
            if axis in sd:
                raise err(j, f"second sd{axis} column (also {_col(names, sd[axis][0])})")
            sd[axis] = (j, unit)
        elif m := _P_RE.match(name):
            pressure.append((int(m.group(1)), j, m.group(2)))
        elif name in ("t_s", "temp_c", *_GYRO_COLUMNS) or (kind == "poses" and name in ("duration_s", "n")):
            pass
        else:
            extra.append(j)

    if "t_s" not in seen:
        raise _error(path, line_no, 1, f"missing required column 't_s' (header: {','.join(names)})")
    unit = None
    for axis in _AXES:
        if axis not in acc:
            expected = f"a{axis}_{unit}" if unit else f"a{axis}_g, a{axis}_mps2 or a{axis}_counts"
            raise _error(path, line_no, 1, f"missing required column {expected} (header: {','.join(names)})")
        j, u = acc[axis]
        if unit is None:
            unit, ref = u, j
        elif u != unit:
            raise err(j, f"mixed acceleration units: {names[ref]!r} is in {unit} but {names[j]!r} is in {u}")
    assert unit is not None

    sd_cols = None
    duration = nn = None
    if kind == "poses":
        sd_cols = []
        for axis in _AXES:
            if axis not in sd:
                raise _error(path, line_no, 1, f"missing required column 'sd{axis}_{unit}' for kind=poses")
            j, u = sd[axis]
            if u != unit:
                raise err(j, f"sd unit {u!r} differs from the acceleration unit {unit!r}")
            sd_cols.append(j)
        if "duration_s" not in seen:
            raise _error(path, line_no, 1, "missing required column 'duration_s' for kind=poses")
        duration, nn = seen["duration_s"], seen.get("n")

    gyro = None
    present = [g for g in _GYRO_COLUMNS if g in seen]
    if present:
        missing = [g for g in _GYRO_COLUMNS if g not in seen]
        if missing:
            raise err(seen[present[0]], f"gyro columns need all of {', '.join(_GYRO_COLUMNS)}; missing {', '.join(missing)}")
        gyro = [seen[g] for g in _GYRO_COLUMNS]

    pressure.sort()
    p_unit = None
    for idx, j, u in pressure:
        if p_unit is None:
            p_unit, ref = u, j
        elif u != p_unit:
            raise err(j, f"mixed pressure units: {names[ref]!r} is in {p_unit} but {names[j]!r} is in {u}")
    for (a, _, _), (b, j, _) in zip(pressure, pressure[1:]):
        if a == b:
            raise err(j, f"pressure cell p{b} appears twice")

    return _Layout(
        t=seen["t_s"],
        acc=[acc[a][0] for a in _AXES],
        unit=unit,
        sd=sd_cols,
        duration=duration,
        n=nn,
        temp=seen.get("temp_c"),
        gyro=gyro,
        pressure=[j for _, j, _ in pressure],
        pressure_unit=p_unit,
        extra=extra,
    )


def _to_float(cells: list[str], n_rows: int, n_cols: int):
    """Fast path: one vectorised conversion. Returns (values, None) or (None, strs)."""
    try:
        return np.array(cells, dtype=np.float64).reshape(n_rows, n_cols), None
    except ValueError:
        return None, np.array(cells, dtype=str).reshape(n_rows, n_cols)


def _strip(strs: np.ndarray) -> np.ndarray:
    strings = getattr(np, "strings", None)  # numpy >= 2: ufunc-based, fast
    return strings.strip(strs) if strings is not None else np.char.strip(strs)


def _first_bad_cell(column: np.ndarray, blank: np.ndarray) -> int:
    """Index of the first non-blank cell that does not parse as a float (error path only)."""
    for k, (text, is_blank) in enumerate(zip(column.tolist(), blank.tolist())):
        if is_blank:
            continue
        try:
            float(text)
        except ValueError:
            return k
    return -1


def _parse_body(path, names, layout, rows, line_nos):
    """Convert the data rows; return (values (m, c) float, text columns, blank mask)."""
    n_rows, n_cols = len(rows), len(names)
    values, strs = _to_float(",".join(rows).split(","), n_rows, n_cols)
    text_cols: dict[int, np.ndarray] = {}
    if values is not None:
        return values, text_cols, None
    stripped = _strip(strs)
    blank = stripped == ""
    values = np.empty((n_rows, n_cols), dtype=np.float64)
    extra = set(layout.extra)
    first_bad: tuple[int, int] | None = None
    for j in range(n_cols):  # column-wise: each conversion is vectorised
        try:
            values[:, j] = np.where(blank[:, j], "nan", strs[:, j]).astype(np.float64)
        except ValueError:
            if j in extra:
                text_cols[j] = stripped[:, j]
                values[:, j] = np.nan
                continue
            k = _first_bad_cell(strs[:, j], blank[:, j])
            if first_bad is None or (k, j) < first_bad:
                first_bad = (k, j)
    if first_bad is not None:
        k, j = first_bad
        if k < 0:  # numpy and Python disagree on some spelling: name the column at least
            raise _error(path, int(line_nos[0]), j + 1, f"{_col(names, j)}: non-numeric value")
        raise _error(path, int(line_nos[k]), j + 1, f"{_col(names, j)}: non-numeric value {strs[k, j].strip()!r}")
    return values, text_cols, blank


def read_recording(path: str | os.PathLike) -> Recording:
    """Read a recording file (samples or poses table).

    Parameters
    ----------
    path : str or path-like
        CSV file following the recording contract (module docstring).

    Returns
    -------
    rec : Recording
        Arrays in the file's units; ``rec.meta['dropped_rows']`` counts rows dropped
        for a blank ``t_s``/acceleration/``sd`` cell.

    Raises
    ------
    InputError
        ``"path:LINE:COL: reason"`` for a missing magic line, unknown or missing kind,
        missing required column, mixed or unknown units, ragged row, non-numeric cell,
        NaN/inf text in ``t_s``/acceleration/``sd``, decreasing ``t_s``, empty table,
        non-integer ``n``; ``"path: reason"`` if the file cannot be read.
    """
    name = os.fspath(path)
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{name}: is a directory, not a recording file")
    if p.suffix.lower() in BINARY_DEVICE_SUFFIXES:
        from selfcal.devices import read_device

        return read_device(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{name}: not UTF-8 text ({exc.reason} at byte {exc.start}); {_ACCEPTED}") from exc
    except FileNotFoundError as exc:
        raise InputError(f"{name}: no such file") from exc
    except OSError as exc:
        raise InputError(f"{name}: cannot read the file ({exc.strerror or exc})") from exc
    if not text.strip():
        raise InputError(f"{name}: the file is empty")
    if "\r" in text:
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    lines = text.split("\n")

    h, kind, meta = _parse_preamble(name, lines)
    header_line = h + 1
    names = [c.strip() for c in lines[h].split(",")]
    layout = _parse_header(name, header_line, names, kind)
    rec = _parse_block(name, names, layout, kind, meta, lines[h + 1:], h + 2, header_line, None)
    if rec is None:
        raise _error(name, header_line, 1, "empty table: no data rows after the header row")
    rec.__dict__.pop("_last_line", None)
    return rec


def _parse_block(name: str, names: list[str], layout: "_Layout", kind: str, meta: dict[str, str],
                 body: list[str], first_line: int, header_line: int, prev_t: float | None,
                 prev_line: int | None = None) -> Recording | None:
    """Parse data lines (``body``, the first at file line ``first_line``) into a Recording.

    Every check of :func:`read_recording` applies, with the file's line numbers;
    ``prev_t`` (s) is the last time of the previous block (``t_s`` must not decrease
    across blocks). Returns None when the block holds no data row.
    """
    n_cols = len(names)
    keep = [k for k, line in enumerate(body) if (s := line.strip()) and s[0] != "#"]
    if not keep:
        return None
    rows = body if len(keep) == len(body) else [body[k] for k in keep]
    line_nos = np.asarray(keep, dtype=np.int64) + first_line

    n_fields = np.fromiter((r.count(",") for r in rows), dtype=np.int64, count=len(rows)) + 1
    ragged = np.flatnonzero(n_fields != n_cols)
    if ragged.size:
        k = int(ragged[0])
        nf = int(n_fields[k])
        if nf > n_cols:
            raise _error(name, int(line_nos[k]), n_cols + 1,
                         f"ragged row: {nf} fields but the header has {n_cols} columns (extra field)")
        raise _error(name, int(line_nos[k]), nf + 1,
                     f"ragged row: {nf} fields but the header has {n_cols} columns "
                     f"({_col(names, nf)} is missing)")

    values, text_cols, blank = _parse_body(name, names, layout, rows, line_nos)

    req = layout.required()
    sub = values[:, req]
    bad = ~np.isfinite(sub)
    if blank is not None:
        bad &= ~blank[:, req]
    if bad.any():
        k, jj = np.argwhere(bad)[0]
        j = req[jj]
        what = "NaN" if np.isnan(sub[k, jj]) else ("inf" if sub[k, jj] > 0 else "-inf")
        raise _error(name, int(line_nos[k]), j + 1,
                     f"{_col(names, j)}: {what} value not allowed in t_s, acceleration or sd "
                     "(leave the cell blank for missing data)")
    n_dropped = 0
    if blank is not None:
        drop = blank[:, req].any(axis=1)
        n_dropped = int(drop.sum())
        if n_dropped:
            keep_rows = ~drop
            values, line_nos = values[keep_rows], line_nos[keep_rows]
            text_cols = {j: col[keep_rows] for j, col in text_cols.items()}
            if values.shape[0] == 0:
                if prev_t is not None:
                    return None
                raise _error(name, header_line, 1,
                             f"empty table: all {n_dropped} data rows have a blank t_s, acceleration or sd cell")

    t_s = values[:, layout.t]
    if prev_t is not None and t_s[0] < prev_t:
        raise _error(name, int(line_nos[0]), layout.t + 1,
                     f"{_col(names, layout.t)}: t_s decreases ({float(t_s[0])!r} after {float(prev_t)!r}"
                     + (f" on line {prev_line})" if prev_line is not None else ")"))
    back = np.flatnonzero(np.diff(t_s) < 0)
    if back.size:
        k = int(back[0]) + 1
        raise _error(name, int(line_nos[k]), layout.t + 1,
                     f"{_col(names, layout.t)}: t_s decreases ({float(t_s[k])!r} after {float(t_s[k - 1])!r} "
                     f"on line {int(line_nos[k - 1])})")

    n_windows = None
    if layout.n is not None:
        n_float = values[:, layout.n]
        bad_n = np.flatnonzero(~(np.isfinite(n_float) & (n_float >= 0) & (n_float == np.round(n_float))))
        if bad_n.size:
            k = int(bad_n[0])
            raise _error(name, int(line_nos[k]), layout.n + 1,
                         f"{_col(names, layout.n)}: samples per window must be a whole number >= 0, "
                         f"got {float(n_float[k])!r}")
        n_windows = n_float.astype(np.int64)

    extra = {names[j]: (text_cols[j] if j in text_cols else values[:, j].copy()) for j in layout.extra}
    rec = _block_recording(name, kind, layout, meta, values, n_windows, extra, n_dropped)
    rec._last_line = int(line_nos[-1])  # for the next block's t_s check (not a field, not in meta)
    return rec


def _block_recording(name: str, kind: str, layout: "_Layout", meta: dict[str, str], values: np.ndarray,
                     n_windows: np.ndarray | None, extra: dict, n_dropped: int) -> Recording:
    """The Recording of a parsed block: the columns of ``values`` (rows, columns) where ``layout`` puts them."""

    def cols(idx):
        return None if idx is None else np.ascontiguousarray(values[:, idx])

    return Recording(
        kind=kind,
        unit=layout.unit,
        t_s=np.ascontiguousarray(values[:, layout.t]),
        acc=cols(layout.acc),
        temp_c=cols(layout.temp),
        pressure=cols(layout.pressure) if layout.pressure else None,
        pressure_unit=layout.pressure_unit,
        gyro_dps=cols(layout.gyro),
        sd=cols(layout.sd),
        duration_s=cols(layout.duration),
        n=n_windows,
        extra=extra,
        meta=dict(meta, dropped_rows=str(n_dropped)),
        path=name,
    )


class _FastBlocks:
    """pyarrow's C CSV parser for blocks that need none of the exact parser's judgement.

    ``parse`` returns a Recording only when the block is clean: every cell numeric and
    present, every required value finite, ``t_s`` non-decreasing (also across the block
    edge), no comment line. Otherwise it returns None and the caller runs the exact
    parser, which gives the same arrays or the line-numbered error.
    """

    def __init__(self, names, layout, kind, meta, name):
        self.names, self.layout, self.kind, self.meta, self.name = names, layout, kind, meta, name
        try:
            import pyarrow as pa
            import pyarrow.csv as pacsv
        except ImportError:  # optional: the exact parser does everything, slower
            self.ok = False
            return
        self.ok = len(set(names)) == len(names)
        self.pa, self.pacsv = pa, pacsv
        self.header = (",".join(names) + "\n").encode("utf-8")

    def parse(self, chunk: list[bytes], first_line: int, prev_t: float | None) -> Recording | None:
        if not self.ok:
            return None
        data = b"".join(chunk)
        if b"#" in data or b"\r" in data:
            return None
        pa, pacsv = self.pa, self.pacsv
        try:
            table = pacsv.read_csv(
                pa.py_buffer(self.header + data),
                read_options=pacsv.ReadOptions(use_threads=False, block_size=max(1 << 20, len(data) + 1024)),
                parse_options=pacsv.ParseOptions(newlines_in_values=False),
                convert_options=pacsv.ConvertOptions(column_types={n: pa.float64() for n in self.names},
                                                     strings_can_be_null=False, quoted_strings_can_be_null=False),
            )
        except (pa.ArrowInvalid, pa.ArrowTypeError, ValueError):
            return None
        if table.num_rows != len(chunk) or any(col.null_count for col in table.columns):
            return None  # blank lines or cells: the exact parser's semantics
        values = np.column_stack([table.column(i).to_numpy() for i in range(len(self.names))])
        lay = self.layout
        if not np.all(np.isfinite(values[:, lay.required()])):
            return None
        t_s = values[:, lay.t]
        if (prev_t is not None and t_s[0] < prev_t) or np.any(np.diff(t_s) < 0):
            return None
        n_windows = None
        if lay.n is not None:
            nf = values[:, lay.n]
            if not np.all(np.isfinite(nf) & (nf >= 0) & (nf == np.round(nf))):
                return None
            n_windows = nf.astype(np.int64)

        rec = _block_recording(self.name, self.kind, lay, self.meta, values, n_windows,
                               {self.names[j]: values[:, j].copy() for j in lay.extra}, 0)
        rec._last_line = first_line + len(chunk) - 1
        return rec


def plain_columns(columns: str | list[str], unit: str | None = None) -> list[str]:
    """Column names for a plain CSV (no selfcal header): ``"t_s,ax_g,ay_g,az_g"``.

    Bare names take ``unit`` (``g``, ``mps2`` or ``counts``): ``t`` or ``time`` becomes
    ``t_s``; ``x``/``ax``, ``y``/``ay``, ``z``/``az`` become ``ax_<unit>``...; ``temp`` or
    ``temperature`` becomes ``temp_c``. Names that carry a unit are kept.
    """
    names = [c.strip() for c in (columns.split(",") if isinstance(columns, str) else columns) if c.strip()]
    bare = {"t": "t_s", "time": "t_s", "temp": "temp_c", "temperature": "temp_c"}
    out = []
    for n in names:
        low = n.lower()
        if low in bare:
            out.append(bare[low])
        elif low in ("x", "y", "z", "ax", "ay", "az"):
            if unit is None:
                raise InputError(f"--columns: {n!r} has no unit; give --unit g, mps2 or counts, or name it "
                                 f"a{low[-1]}_g (the unit in the name)")
            out.append(f"a{low[-1]}_{unit}")
        else:
            out.append(n)
    # the columns must name a time and three axes: the fault is the option's, not the file's line
    missing = ([] if "t_s" in out else ["t (t_s)"]) + [
        f"{a} (a{a}_g, a{a}_mps2 or a{a}_counts)" for a in "xyz"
        if not any(re.fullmatch(rf"a{a}_(g|mps2|counts)", c) for c in out)]
    if missing:
        raise InputError(f"--columns {','.join(names)}: no column for {', '.join(missing)}")
    return out


def iter_recording(path: str | os.PathLike, block_rows: int = 100_000, progress=None,
                   columns: list[str] | None = None) -> Iterator[Recording]:
    """Stream a recording in blocks of at most ``block_rows`` rows, in bounded memory.

    ``columns`` (see :func:`plain_columns`) reads a plain CSV with no selfcal header as a
    samples table with these columns; a first line that is not numbers is taken as the
    file's own header and skipped.

    Yields :class:`Recording` blocks (same kind, unit and columns; ``meta['dropped_rows']``
    per block). Every check and error of :func:`read_recording` applies, with the file's
    own line numbers, including rows of the last block and a ``t_s`` that decreases
    across a block edge. Device files (decoded whole by actfast) come as one block.
    ``progress(n_bytes)`` is called after each block with the bytes read so far.
    """
    name = os.fspath(path)
    p = Path(path)
    if p.is_dir():
        raise InputError(f"{name}: is a directory, not a recording file")
    if p.suffix.lower() in BINARY_DEVICE_SUFFIXES:
        yield read_recording(path)
        return
    if block_rows < 1:
        raise InputError(f"block_rows must be >= 1, got {block_rows}")
    try:
        fh = p.open("rb")
    except FileNotFoundError as exc:
        raise InputError(f"{name}: no such file") from exc
    except OSError as exc:
        raise InputError(f"{name}: cannot read the file ({exc.strerror or exc})") from exc
    with fh:
        def decode(raw: bytes, at_line: int) -> str:
            try:
                return raw.decode("utf-8")
            except UnicodeDecodeError as exc:  # the line of the bad byte, not the block's first
                line = at_line + raw.count(b"\n", 0, exc.start)
                raise InputError(f"{name}:{line}: not UTF-8 text ({exc.reason}); {_ACCEPTED}") from exc

        def line_of(raw: bytes) -> bytes:  # a line ended by a lone CR (old Mac) would be the whole file
            end = raw.find(b"\r")
            if 0 <= end < len(raw) - 2 and raw[end + 1:end + 2] != b"\n":
                raise InputError(f"{name}: lines end with a lone CR (classic Mac OS); convert the file to "
                                 "LF or CRLF line endings")
            if len(raw) >= _MAX_HEAD_LINE and not raw.endswith(b"\n"):
                raise InputError(f"{name}: a line of the preamble is longer than {_MAX_HEAD_LINE} bytes: not a "
                                 f"recording; {_ACCEPTED}")
            return raw

        head = fh.read(65536)  # a binary file is refused up front, naming what is accepted
        try:
            head.decode("utf-8")
            binary = b"\x00" in head
        except UnicodeDecodeError as exc:
            binary = exc.start < len(head) - 4  # not just a character cut at the end of the peek
        if binary:
            raise InputError(f"{name}: not UTF-8 text (binary data); {_ACCEPTED}")
        fh.seek(0)
        pre: list[str] = []
        if columns is not None:  # a plain CSV: our preamble in place of the missing one
            first = line_of(fh.readline(_MAX_HEAD_LINE))
            skipped = 0
            bom = 3 if first.startswith(b"\xef\xbb\xbf") else 0  # (a BOM before a data row hid its first number)
            try:
                [float(x) for x in decode(first[bom:], 1).strip().split(",")]
                fh.seek(bom)
            except ValueError:
                skipped = 1  # the file's own header row
            pre = [MAGIC_LINE, "# kind=samples", ",".join(columns)]
        while columns is None:  # the preamble and the header row
            raw = line_of(fh.readline(_MAX_HEAD_LINE))
            if not raw:
                break
            line = decode(raw, len(pre) + 1)
            if not pre:
                line = line.lstrip("\ufeff")
            line = line.rstrip("\r\n")
            pre.append(line)
            s_ = line.strip()
            if s_ and not s_.startswith("#"):
                break
        if not any(x.strip() for x in pre):
            raise InputError(f"{name}: the file is empty")
        h, kind, meta = _parse_preamble(name, pre)
        header_line = h + 1
        names = [c.strip() for c in pre[h].split(",")]
        layout = _parse_header(name, header_line, names, kind)
        next_line = h + 2
        if columns is not None:  # line numbers are the file's own
            header_line, next_line = max(skipped, 1), 1 + skipped
            meta = {"columns": ",".join(columns)}
        prev_t = prev_line = None
        any_rows = False
        fast = _FastBlocks(names, layout, kind, meta, name)
        while True:
            chunk = list(itertools.islice(fh, block_rows))
            if not chunk:
                break
            rec = fast.parse(chunk, next_line, prev_t)  # pyarrow, when the block is clean
            if rec is None:  # anything unusual: the exact parser, with its line-numbered errors
                body = decode(b"".join(chunk), next_line).replace("\r\n", "\n").replace("\r", "\n").split("\n")
                if body and body[-1] == "":
                    body.pop()
                rec = _parse_block(name, names, layout, kind, meta, body, next_line, header_line, prev_t, prev_line)
            next_line += len(chunk)
            if progress is not None:
                progress(fh.tell())
            if rec is None:
                continue
            any_rows = True
            prev_t, prev_line = float(rec.t_s[-1]), rec.__dict__.pop("_last_line")
            yield rec
        if not any_rows:
            raise _error(name, header_line, 1, "empty table: no data rows after the header row")


# --------------------------------------------------------------------------- writing



def _reader_claims(name: str, kind: str) -> bool:
    """True if the reader would take column `name` as a contract column (not extra)."""
    if name in ("t_s", "temp_c", *_GYRO_COLUMNS) or _ACC_RE.match(name) or _P_RE.match(name):
        return True
    return kind == "poses" and (name in ("duration_s", "n") or bool(_SD_RE.match(name)))


def _format_column(values: np.ndarray) -> list[str]:
    """Shortest exact text of each value (``repr`` of float/int, NaN as ``nan``)."""
    if values.dtype.kind in "fiub":
        return list(map(repr, values.tolist()))
    return [str(v) for v in values.tolist()]


def write_recording(path: str | os.PathLike, rec: Recording) -> None:
    """Write a recording in the contract format (atomic replace of `path`).

    Parameters
    ----------
    path : str or path-like
        Destination file.
    rec : Recording
        Recording to write. Floats are written with Python's shortest exact
        ``repr``, so :func:`read_recording` gives back identical arrays. Column order:
        ``t_s``, acceleration, (poses: ``sd``, ``duration_s``, ``n``), ``temp_c``,
        pressure, gyro, then ``extra`` in its order. ``meta['dropped_rows']`` is not
        written (the reader derives it).

    Raises
    ------
    InputError
        If `rec` could not be read back: non-finite or decreasing ``t_s``,
        non-finite acceleration/sd, an ``extra`` name that clashes with a contract
        column or holds a comma/newline, a meta key or value that is not one line.
    """
    write_recording_blocks(path, [rec])


def _block_columns(rec: Recording) -> list[tuple[str, np.ndarray]]:
    """Checked ``(name, values)`` columns of one block, in file order."""
    _check_fields(rec)
    where = rec.path or "Recording"
    for name in ("t_s", "acc", "sd"):
        value = getattr(rec, name)
        if value is not None and not np.all(np.isfinite(value)):
            raise InputError(f"{where}: {name} has NaN/inf values; the file format cannot hold them")
    if np.any(np.diff(rec.t_s) < 0):
        raise InputError(f"{where}: t_s decreases; the file format requires non-decreasing t_s")
    columns: list[tuple[str, np.ndarray]] = [("t_s", rec.t_s)]
    columns += [(f"a{a}_{rec.unit}", rec.acc[:, i]) for i, a in enumerate(_AXES)]
    if rec.kind == "poses":
        columns += [(f"sd{a}_{rec.unit}", rec.sd[:, i]) for i, a in enumerate(_AXES)]
        columns.append(("duration_s", rec.duration_s))
        if rec.n is not None:
            columns.append(("n", rec.n))
    if rec.temp_c is not None:
        columns.append(("temp_c", rec.temp_c))
    if rec.pressure is not None:
        columns += [(f"p{i + 1}_{rec.pressure_unit}", rec.pressure[:, i]) for i in range(rec.pressure.shape[1])]
    if rec.gyro_dps is not None:
        columns += [(f"g{a}_dps", rec.gyro_dps[:, i]) for i, a in enumerate(_AXES)]
    for name, value in rec.extra.items():
        if not name or name != name.strip() or any(c in name for c in ",\n\r#") or _reader_claims(name, rec.kind):
            raise InputError(f"{where}: extra column name {name!r} is empty, has ',', '#' or a newline, "
                             "or clashes with a contract column")
        value = np.asarray(value)
        if value.dtype.kind not in "fiub" and any("," in s or "\n" in s for s in map(str, value.tolist())):
            raise InputError(f"{where}: extra column {name!r} has a value with ',' or a newline")
        columns.append((name, value))
    return columns


def _header_lines(rec: Recording, names: list[str]) -> list[str]:
    where = rec.path or "Recording"
    out = [MAGIC_LINE, f"# kind={rec.kind}"]
    for key, value in rec.meta.items():
        if key in _DERIVED_META:
            continue
        if key == "kind" or not re.match(r"^[A-Za-z_][A-Za-z0-9_.\-]*$", key):
            raise InputError(f"{where}: meta key {key!r} is not a valid key (identifier, not 'kind')")
        value = str(value)
        if "\n" in value or "\r" in value:
            raise InputError(f"{where}: meta[{key!r}] spans several lines; meta values must be one line")
        out.append(f"# {key}={value}")
    out.append(",".join(names))
    return out


def write_recording_blocks(path: str | os.PathLike, blocks: Iterable[Recording]) -> int:
    """Write a recording given in blocks, in bounded memory (atomic replace of `path`).

    The first block gives the header (kind, unit, columns, meta); every block must have
    the same columns, and ``t_s`` must not decrease within or across blocks. The same
    checks and errors as :func:`write_recording`; on any error `path` is untouched.

    Returns
    -------
    int
        Rows written.
    """
    target = Path(path)
    # a fresh name opened exclusively: the file gets the user's umask (mkstemp's are 0600)
    tmp = target.parent / f".{target.name}.{secrets.token_hex(8)}.tmp"
    rows = 0
    try:
        with open(tmp, "x", encoding="utf-8", newline="\n") as fh:
            names: list[str] | None = None
            last_t = -np.inf
            for rec in blocks:
                if len(rec) == 0:
                    continue
                columns = _block_columns(rec)
                block_names = [name for name, _ in columns]
                if names is None:
                    names = block_names
                    fh.write("\n".join(_header_lines(rec, names)) + "\n")
                elif block_names != names:
                    raise InputError(f"{rec.path or 'Recording'}: block columns {block_names} differ from {names}")
                if rec.t_s[0] < last_t:
                    raise InputError(f"{rec.path or 'Recording'}: t_s decreases across blocks; the file "
                                     "format requires non-decreasing t_s")
                last_t = float(rec.t_s[-1])
                texts = [_format_column(np.asarray(value)) for _, value in columns]
                fh.write("\n".join(",".join(row) for row in zip(*texts)) + "\n")
                rows += len(rec)
            if names is None:
                raise InputError(f"{target}: no rows to write (the file format has no empty tables)")
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return rows

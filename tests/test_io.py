"""Tests for selfcal.io: the recording file contract (design.md, "Recording files")."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from selfcal import STANDARD_GRAVITY_MPS2
from selfcal.errors import InputError
from selfcal.io import Recording, read_recording, write_recording

DATA_DIR = Path(__file__).resolve().parents[1] / "data"
REAL_FILES = sorted(DATA_DIR.glob("*/*.csv"))

SAMPLES_HEAD = "# selfcal-recording v1\n# kind=samples\n"
POSES_HEAD = "# selfcal-recording v1\n# kind=poses\n"


def _write(tmp_path: Path, text: str, name: str = "rec.csv") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _error_location(path: Path, exc: pytest.ExceptionInfo) -> tuple[int, int, str]:
    """Split 'path:LINE:COL: reason' into (LINE, COL, reason); fail if the form is wrong."""
    message = str(exc.value)
    prefix = f"{path}:"
    assert message.startswith(prefix), message
    m = re.match(r"(\d+):(\d+): (.+)$", message[len(prefix):], re.S)
    assert m is not None, message
    return int(m.group(1)), int(m.group(2)), m.group(3)


# ----------------------------------------------------------------------------- real data


@pytest.mark.skipif(not REAL_FILES, reason=f"no real data under {DATA_DIR}")
@pytest.mark.parametrize("path", REAL_FILES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_real_file_reads(path: Path) -> None:
    rec = read_recording(path)
    n_rows = len(rec)
    assert n_rows > 100
    assert rec.kind in ("samples", "poses")
    assert rec.acc.shape == (n_rows, 3)
    assert np.all(np.isfinite(rec.t_s)) and np.all(np.diff(rec.t_s) >= 0)
    assert np.all(np.isfinite(rec.acc))
    assert rec.meta["dropped_rows"] == "0"
    if rec.unit != "counts":
        norm_g = np.linalg.norm(rec.acc_g(), axis=1)
        # Median norm near 1 g checks the unit (m/s^2 read as g would give ~9.8);
        # short walking files sit higher than still ones.
        assert 0.7 < np.median(norm_g) < 1.5
    else:
        with pytest.raises(InputError, match="counts"):
            rec.acc_g()
    if rec.kind == "samples":
        assert 50.0 < rec.rate_hz() < 250.0
    else:
        assert rec.sd.shape == (n_rows, 3) and rec.duration_s.shape == (n_rows,)


def test_real_moticon_columns() -> None:
    path = DATA_DIR / "moticon-insole" / "230927_102114_left.csv"
    if not path.exists():
        pytest.skip(f"{path} missing")
    rec = read_recording(path)
    assert rec.unit == "g" and rec.pressure_unit == "ncm2"
    assert rec.pressure.shape == (len(rec), 16)
    assert rec.gyro_dps.shape == (len(rec), 3)
    assert list(rec.extra) == ["total_force_n"]
    assert rec.meta["sensor"].startswith("Moticon OpenGo")
    # first data row of the file: p1..p3 = 7.25, 5.25, 6.25 N/cm^2, gz = -0.84 dps
    np.testing.assert_allclose(rec.pressure_kpa()[0, :3], [72.5, 52.5, 62.5])
    assert rec.gyro_dps[0, 2] == -0.84
    assert rec.rate_hz() == pytest.approx(100.0, rel=1e-6)


def test_real_mps2_converts_to_g() -> None:
    path = DATA_DIR / "gaitmap-shoe-walking" / "gaitmap_left.csv"
    if not path.exists():
        pytest.skip(f"{path} missing")
    rec = read_recording(path)
    assert rec.unit == "mps2"
    np.testing.assert_allclose(rec.acc_g()[0], np.array([0.880811, 2.762208, 9.408650]) / 9.80665)
    assert rec.rate_hz() == pytest.approx(204.8, rel=1e-3)


# ----------------------------------------------------------------------------- parsing


def test_units_pressure_order_extra_and_meta(tmp_path: Path) -> None:
    text = (
        "# selfcal-recording v1\n"
        "# sensor=test rig, left foot\n"
        "# a free-text comment: ignored (x = y inside text is not meta)\n"
        "# kind=samples\n"
        "t_s,ax_mps2,ay_mps2,az_mps2,p2_kpa,p10_kpa,p1_kpa,label,temp_c\n"
        "0.0,0,0,9.80665,2,10,1,a,20\n"
        "\n"
        "# comment between rows\n"
        "0.5,9.80665,0,0,4,20,3,b,21\n"
    )
    rec = read_recording(_write(tmp_path, text))
    assert rec.unit == "mps2"
    np.testing.assert_allclose(rec.acc_g(), [[0, 0, 1], [1, 0, 0]])
    # pressure ordered by cell index 1, 2, 10, not by column order
    np.testing.assert_array_equal(rec.pressure, [[1, 2, 10], [3, 4, 20]])
    assert rec.pressure_unit == "kpa"
    np.testing.assert_array_equal(rec.pressure_kpa(), rec.pressure)
    assert rec.extra["label"].tolist() == ["a", "b"]
    np.testing.assert_array_equal(rec.temp_c, [20, 21])
    assert rec.meta == {"sensor": "test rig, left foot", "dropped_rows": "0"}
    assert rec.rate_hz() == pytest.approx(2.0)


def test_blank_acc_cells_drop_rows_blank_optional_cells_are_nan(tmp_path: Path) -> None:
    text = SAMPLES_HEAD + (
        "t_s,ax_g,ay_g,az_g,p1_ncm2,gx_dps,gy_dps,gz_dps\n"
        "0.00,0,0,1,1.5,0,0,0\n"
        "0.01,,,,,,,\n"          # moticon style: sensor sent nothing
        "0.02,0,0,1,,1,2,3\n"    # blank pressure only: kept, NaN
        "0.03,0, ,1,2,1,2,3\n"   # blank (whitespace) ay: dropped
        "0.04,0,0,1,2.5,1,2,3\n"
    )
    rec = read_recording(_write(tmp_path, text))
    np.testing.assert_array_equal(rec.t_s, [0.0, 0.02, 0.04])
    assert rec.meta["dropped_rows"] == "2"
    assert np.isnan(rec.pressure[1, 0]) and rec.pressure[2, 0] == 2.5
    np.testing.assert_allclose(rec.pressure_kpa()[:, 0], [15.0, np.nan, 25.0])


def test_counts_and_unknown_pressure_unit_raise_on_conversion(tmp_path: Path) -> None:
    text = SAMPLES_HEAD + "t_s,ax_counts,ay_counts,az_counts,p1_psi\n0,1,2,3,4\n1,1,2,3,4\n"
    rec = read_recording(_write(tmp_path, text))
    with pytest.raises(InputError, match="counts"):
        rec.acc_g()
    with pytest.raises(InputError, match="'psi'"):
        rec.pressure_kpa()


def test_poses_table(tmp_path: Path) -> None:
    text = POSES_HEAD + (
        "t_s,ax_mps2,ay_mps2,az_mps2,sdx_mps2,sdy_mps2,sdz_mps2,duration_s,n\n"
        "10,0,0,9.80665,0.0980665,0.0980665,0.196133,2.5,250\n"
    )
    rec = read_recording(_write(tmp_path, text))
    assert rec.kind == "poses"
    np.testing.assert_allclose(rec.sd_g(), [[0.01, 0.01, 0.02]])
    assert rec.n.dtype == np.int64 and rec.n.tolist() == [250]
    with pytest.raises(InputError, match="poses"):
        rec.rate_hz()


def test_crlf_and_bom(tmp_path: Path) -> None:
    text = "\ufeff" + SAMPLES_HEAD + "t_s,ax_g,ay_g,az_g\n0,1,2,3\n1,4,5,6\n"
    path = tmp_path / "crlf.csv"
    path.write_bytes(text.replace("\n", "\r\n").encode("utf-8"))
    rec = read_recording(path)
    np.testing.assert_array_equal(rec.acc, [[1, 2, 3], [4, 5, 6]])


def test_missing_file_is_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        read_recording(tmp_path / "nope.csv")


# ----------------------------------------------------------------------------- errors

GOOD_HEADER = "t_s,ax_g,ay_g,az_g"

# (id, file text, expected line, expected column, text the reason must contain)
MALFORMED = [
    ("no-magic", "# kind=samples\n" + GOOD_HEADER + "\n0,0,0,1\n", 1, 1, "selfcal-recording v1"),
    ("no-comments", GOOD_HEADER + "\n0,0,0,1\n", 1, 1, "missing magic line"),
    ("bad-version", "# selfcal-recording v9\n# kind=samples\n" + GOOD_HEADER + "\n0,0,0,1\n", 1, 1, "v9"),
    ("unknown-kind", "# selfcal-recording v1\n# kind=stream\n" + GOOD_HEADER + "\n0,0,0,1\n", 2, 1, "'stream'"),
    ("missing-kind", "# selfcal-recording v1\n" + GOOD_HEADER + "\n0,0,0,1\n", 2, 1, "kind="),
    ("missing-t", SAMPLES_HEAD + "time,ax_g,ay_g,az_g\n0,0,0,1\n", 3, 1, "'t_s'"),
    ("missing-az", SAMPLES_HEAD + "t_s,ax_g,ay_g\n0,0,0\n", 3, 1, "az_g"),
    ("mixed-units", SAMPLES_HEAD + "t_s,ax_g,ay_mps2,az_g\n0,0,0,1\n", 3, 3, "column 3 'ay_mps2': mixed"),
    ("unknown-acc-unit", SAMPLES_HEAD + "t_s,ax_g,ay_g,az_furlong\n0,0,0,1\n", 3, 4, "'furlong'"),
    ("duplicate-column", SAMPLES_HEAD + "t_s,ax_g,ay_g,az_g,temp_c,temp_c\n0,0,0,1,2,2\n", 3, 6, "duplicate"),
    ("mixed-pressure", SAMPLES_HEAD + GOOD_HEADER + ",p1_ncm2,p2_kpa\n0,0,0,1,1,1\n", 3, 6, "column 6 'p2_kpa'"),
    ("poses-sd-unit", POSES_HEAD + "t_s,ax_g,ay_g,az_g,sdx_g,sdy_mps2,sdz_g,duration_s\n0,0,0,1,0,0,0,1\n",
     3, 6, "column 6 'sdy_mps2'"),
    ("poses-missing-sd", POSES_HEAD + "t_s,ax_g,ay_g,az_g,sdx_g,sdy_g,duration_s\n0,0,0,1,0,0,1\n", 3, 1, "sdz_g"),
    ("poses-missing-duration", POSES_HEAD + "t_s,ax_g,ay_g,az_g,sdx_g,sdy_g,sdz_g\n0,0,0,1,0,0,0\n",
     3, 1, "duration_s"),
    ("ragged-short", SAMPLES_HEAD + GOOD_HEADER + "\n0,0,0,1\n1,0,0\n", 5, 4, "column 4 'az_g' is missing"),
    ("ragged-long", SAMPLES_HEAD + GOOD_HEADER + "\n0,0,0,1\n1,0,0,1\n2,0,0,1,7\n", 6, 5, "extra field"),
    ("non-numeric", SAMPLES_HEAD + GOOD_HEADER + "\n0,0,0,1\n1,0,abc,1\n", 5, 3, "column 3 'ay_g': non-numeric value 'abc'"),
    ("non-numeric-temp", SAMPLES_HEAD + GOOD_HEADER + ",temp_c\n0,0,0,1,20\n1,0,0,1,warm\n", 5, 5, "'warm'"),
    ("nan-in-acc", SAMPLES_HEAD + GOOD_HEADER + "\n0,0,0,1\n1,0,0,1\n2,NaN,0,1\n", 6, 2, "column 2 'ax_g': NaN"),
    ("inf-in-acc", SAMPLES_HEAD + GOOD_HEADER + "\n0,0,0,1\n1,0,0,-inf\n", 5, 4, "column 4 'az_g': -inf value"),
    ("nan-in-t", SAMPLES_HEAD + GOOD_HEADER + "\n0,0,0,1\nnan,0,0,1\n", 5, 1, "column 1 't_s': NaN"),
    ("nan-with-blank", SAMPLES_HEAD + GOOD_HEADER + "\n0,,0,1\n1,0,nan,1\n", 5, 3, "'ay_g': NaN"),
    ("decreasing-t", SAMPLES_HEAD + GOOD_HEADER + "\n0,0,0,1\n0.2,0,0,1\n# note\n0.1,0,0,1\n", 7, 1, "t_s decreases (0.1 after 0.2 on line 5)"),
    ("empty-table", SAMPLES_HEAD + GOOD_HEADER + "\n\n", 3, 1, "empty table"),
    ("all-rows-blank", SAMPLES_HEAD + GOOD_HEADER + "\n0,,,\n1,,,\n", 3, 1, "empty table"),
    ("only-comments", "# selfcal-recording v1\n# kind=samples\n", 3, 1, "no header row"),
    ("bad-n", POSES_HEAD + "t_s,ax_g,ay_g,az_g,sdx_g,sdy_g,sdz_g,duration_s,n\n0,0,0,1,0,0,0,1,2.5\n",
     4, 9, "column 9 'n'"),
    ("partial-gyro", SAMPLES_HEAD + GOOD_HEADER + ",gx_dps,gy_dps\n0,0,0,1,0,0\n", 3, 5, "gz_dps"),
]


@pytest.mark.parametrize(("text", "line", "col", "needle"), [m[1:] for m in MALFORMED], ids=[m[0] for m in MALFORMED])
def test_malformed_file_names_line_and_column(tmp_path: Path, text: str, line: int, col: int, needle: str) -> None:
    path = _write(tmp_path, text)
    with pytest.raises(InputError) as exc:
        read_recording(path)
    got_line, got_col, reason = _error_location(path, exc)
    assert (got_line, got_col) == (line, col), str(exc.value)
    assert needle in reason, str(exc.value)


def test_error_in_large_file_points_at_exact_line(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    acc = rng.normal(size=(5000, 3))
    lines = [f"{0.01 * i:.2f},{a:.6f},{b:.6f},{c:.6f}" for i, (a, b, c) in enumerate(acc)]
    lines[4321] = lines[4321].rsplit(",", 1)[0] + ",1.0.0"
    path = _write(tmp_path, SAMPLES_HEAD + GOOD_HEADER + "\n" + "\n".join(lines) + "\n")
    with pytest.raises(InputError) as exc:
        read_recording(path)
    # 2 comment lines + header line, then row index 4321 is file line 4325
    assert _error_location(path, exc)[:2] == (4325, 4)


# ----------------------------------------------------------------------------- round trip


def _samples(rng: np.random.Generator, n_rows: int, temp: bool, pressure: bool, gyro: bool) -> Recording:
    t_s = np.cumsum(rng.uniform(0.005, 0.015, n_rows))
    return Recording(
        kind="samples",
        unit="g",
        t_s=t_s,
        acc=rng.normal(0.0, 1.0, (n_rows, 3)),
        temp_c=rng.uniform(15, 35, n_rows) if temp else None,
        pressure=rng.uniform(0, 30, (n_rows, 4)) if pressure else None,
        pressure_unit="ncm2" if pressure else None,
        gyro_dps=rng.normal(0, 100, (n_rows, 3)) if gyro else None,
        extra={"total_force_n": rng.uniform(0, 900, n_rows)} if pressure else {},
        meta={"sensor": "synthetic, seed 1", "device_id": "L-42"},
    )


def _assert_same(a: Recording, b: Recording) -> None:
    assert (a.kind, a.unit, a.pressure_unit) == (b.kind, b.unit, b.pressure_unit)
    for name in ("t_s", "acc", "temp_c", "pressure", "gyro_dps", "sd", "duration_s", "n"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)  # bit-exact, NaN == NaN
    assert list(a.extra) == list(b.extra)
    for key in a.extra:
        np.testing.assert_array_equal(a.extra[key], b.extra[key], err_msg=key)
    strip = lambda m: {k: v for k, v in m.items() if k != "dropped_rows"}  # noqa: E731
    assert strip(a.meta) == strip(b.meta)


@pytest.mark.parametrize(("temp", "pressure", "gyro"), [(False, False, False), (True, False, False),
                                                       (False, True, True), (True, True, True)])
def test_round_trip_samples(tmp_path: Path, temp: bool, pressure: bool, gyro: bool) -> None:
    rng = np.random.default_rng(1)
    rec = _samples(rng, 300, temp, pressure, gyro)
    if temp:
        rec.temp_c[5] = np.nan  # missing optional data survives as NaN
    path = tmp_path / "out.csv"
    write_recording(path, rec)
    back = read_recording(path)
    _assert_same(rec, back)
    assert back.meta["dropped_rows"] == "0"
    # writing what was read gives the same bytes
    path2 = tmp_path / "out2.csv"
    write_recording(path2, back)
    assert path2.read_bytes() == path.read_bytes()


@pytest.mark.parametrize("with_n", [False, True])
@pytest.mark.parametrize("unit", ["g", "counts"])
def test_round_trip_poses(tmp_path: Path, with_n: bool, unit: str) -> None:
    rng = np.random.default_rng(2)
    m = 50
    scale = 1.0 if unit == "g" else 4050.0
    rec = Recording(
        kind="poses",
        unit=unit,
        t_s=np.arange(m) * 10.0,
        acc=rng.normal(0, 1, (m, 3)) * scale + (32768.0 if unit == "counts" else 0.0),
        temp_c=rng.uniform(15, 35, m),
        sd=rng.uniform(0.001, 0.013, (m, 3)) * scale,
        duration_s=np.full(m, 10.0),
        n=rng.integers(100, 1000, m) if with_n else None,
    )
    path = tmp_path / "poses.csv"
    write_recording(path, rec)
    back = read_recording(path)
    _assert_same(rec, back)
    assert "kind=poses" in path.read_text().splitlines()[1]


def test_round_trip_real_file(tmp_path: Path) -> None:
    src = DATA_DIR / "moticon-insole" / "220915_walking_text_export_left.csv"
    if not src.exists():
        pytest.skip(f"{src} missing")
    rec = read_recording(src)
    write_recording(tmp_path / "copy.csv", rec)
    _assert_same(rec, read_recording(tmp_path / "copy.csv"))


def test_write_rejects_unreadable_records(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    rec = _samples(rng, 10, False, False, False)
    rec.acc[3, 1] = np.nan
    with pytest.raises(InputError, match="acc has NaN"):
        write_recording(tmp_path / "x.csv", rec)
    rec = _samples(rng, 10, False, False, False)
    rec.extra["ax_g"] = np.zeros(10)
    with pytest.raises(InputError, match="clashes"):
        write_recording(tmp_path / "x.csv", rec)
    assert not (tmp_path / "x.csv").exists()


def test_a_written_recording_gets_the_users_umask_and_leaves_no_temporary_file(tmp_path: Path) -> None:
    """Recordings were written through mkstemp, whose files are 0600: another user of the
    group could not read a file the same user writes with any other tool."""
    import os

    rec = _samples(np.random.default_rng(4), 10, False, False, False)
    old = os.umask(0o022)
    try:
        write_recording(tmp_path / "x.csv", rec)
    finally:
        os.umask(old)
    assert (tmp_path / "x.csv").stat().st_mode & 0o777 == 0o644
    assert [p.name for p in tmp_path.iterdir()] == ["x.csv"]


def test_recording_checks_shapes() -> None:
    with pytest.raises(InputError, match="acc must have shape"):
        Recording(kind="samples", unit="g", t_s=np.zeros(4), acc=np.zeros((4, 2)))
    with pytest.raises(InputError, match="unit must be one of"):
        Recording(kind="samples", unit="G", t_s=np.zeros(4), acc=np.zeros((4, 3)))
    with pytest.raises(InputError, match="whole numbers"):
        Recording(kind="poses", unit="g", t_s=np.zeros(1), acc=np.zeros((1, 3)), sd=np.zeros((1, 3)),
                  duration_s=np.ones(1), n=np.array([np.nan]))
    with pytest.raises(InputError, match="poses recording needs sd"):
        Recording(kind="poses", unit="g", t_s=np.zeros(4), acc=np.zeros((4, 3)))


def test_acc_g_divides_by_standard_gravity() -> None:
    rec = Recording(kind="samples", unit="mps2", t_s=np.array([0.0, 0.1]),
                    acc=np.array([[STANDARD_GRAVITY_MPS2, 0, 0], [0, 0, -2 * STANDARD_GRAVITY_MPS2]]))
    np.testing.assert_allclose(rec.acc_g(), [[1, 0, 0], [0, 0, -2]], rtol=0, atol=1e-15)
    assert rec.acc[0, 0] == STANDARD_GRAVITY_MPS2  # acc_g returns a new array

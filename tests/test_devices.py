"""Device files (Axivity .cwa, ActiGraph .gt3x, GENEActiv .bin) through actfast: read, calibrate, refuse cut copies.

The GENEActiv file is synthetic (tests/geneactivgen.py): no real .bin is available.
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import selfcal
from geneactivgen import HEX_PER_SAMPLE, SAMPLES_PER_PAGE, write_fixture, write_geneactiv_bin
from selfcal.errors import InputError

pytest.importorskip("actfast")
ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "device-formats"


@pytest.mark.parametrize("name,temp", [("axivity_ax3.cwa", True), ("axivity_ax6.cwa", True), ("actigraph.gt3x", False)])
def test_device_files_read_as_samples_in_g(name, temp):
    rec = selfcal.read(DATA / name)
    assert rec.kind == "samples" and rec.unit == "g"
    assert rec.acc.dtype == np.float32 and rec.acc.shape[1] == 3 and len(rec) > 1000
    assert rec.t_s[0] == 0 and np.all(np.diff(rec.t_s) >= 0)
    assert 20 < rec.rate_hz() < 250
    norm = np.linalg.norm(rec.acc, axis=1)
    assert np.max(norm) < 40 and np.mean(np.abs(norm - 1) < 0.1) > 0.05  # in g: some stills near 1 g
    assert (rec.temp_c is not None) == temp
    if temp:
        assert rec.temp_c.dtype == np.float32 and 0 < np.nanmedian(rec.temp_c) < 45
    assert float(rec.meta["start_unix_s"]) > 1e9


def test_device_file_through_the_calibrator_gives_a_typed_refusal():
    # the fixtures last 12-36 s: too short to calibrate, and that must be said, not crash
    with pytest.raises(selfcal.api.CalibrationError) as exc:
        selfcal.calibrate(DATA / "axivity_ax3.cwa")
    assert exc.value.reason in ("insufficient_coverage", "no_still_poses")


def test_truncated_or_garbage_device_file_is_an_input_error(tmp_path):
    bad = tmp_path / "cut.cwa"
    bad.write_bytes((DATA / "axivity_ax3.cwa").read_bytes()[:700])  # inside the header
    with pytest.raises(InputError, match="cut.cwa"):
        selfcal.read(bad)
    mid = tmp_path / "mid.cwa"  # cut inside a data sector: actfast alone would drop it silently
    raw = (DATA / "axivity_ax3.cwa").read_bytes()
    mid.write_bytes(raw[: 1024 + 3 * 512 + 100])
    with pytest.raises(InputError, match="truncated"):
        selfcal.read(mid)
    junk = tmp_path / "junk.gt3x"
    junk.write_bytes(b"\x00" * 4096)
    with pytest.raises(InputError, match="junk.gt3x"):
        selfcal.read(junk)


def test_geneactiv_fixture_reads_as_samples_in_g_with_temperature(tmp_path):
    rec = selfcal.read(DATA / "geneactiv_synthetic.bin")
    assert rec.kind == "samples" and rec.unit == "g" and rec.meta["format"] == "GeneActiv BIN"
    assert rec.acc.dtype == np.float32 and rec.acc.shape == (4 * SAMPLES_PER_PAGE, 3)
    assert rec.t_s[0] == 0 and np.all(np.diff(rec.t_s) > 0) and rec.rate_hz() == pytest.approx(10.0)
    norm = np.linalg.norm(rec.acc, axis=1)
    assert np.all(np.abs(norm - 1) < 0.06)  # still poses and slow turns, with a ~30 mg sensor error
    assert rec.temp_c.dtype == np.float32
    assert rec.temp_c[0] == pytest.approx(22.0) and rec.temp_c[-1] == pytest.approx(25.5)
    assert np.all(np.diff(rec.temp_c) >= 0)  # one value a page, interpolated between pages
    assert float(rec.meta["start_unix_s"]) == pytest.approx(1_714_490_010.0)
    # the committed file is exactly what its generator writes (PROVENANCE.txt)
    content = write_fixture(tmp_path / "again.bin")
    assert (tmp_path / "again.bin").read_bytes() == (DATA / "geneactiv_synthetic.bin").read_bytes()
    np.testing.assert_array_equal(rec.acc, content.acc_g.astype(np.float32))


@pytest.mark.parametrize("rate_hz,newline", [(100.0, "\r\n"), (30.0, "\n")])
def test_geneactiv_round_trip_of_known_acceleration_and_temperature(tmp_path, rate_hz, newline):
    rng = np.random.default_rng(7)
    n = 3 * SAMPLES_PER_PAGE
    acc = rng.uniform(-7.5, 7.5, (n, 3))
    temps = np.array([18.25, 31.5, 24.0])
    path = tmp_path / "known.bin"
    start = 1_700_000_000.25
    content = write_geneactiv_bin(path, acc, rate_hz, temps, start_unix_s=start, gains=(25000, 26000, 25600),
                                  offsets=(500, -2000, 0), newline=newline)
    rec = selfcal.read(path)
    assert rec.acc.shape == (n, 3) and rec.acc.dtype == np.float32
    # within half a 12-bit count of the input, and exactly the calibrated counts
    assert np.all(np.abs(rec.acc - acc) <= content.quant_g / 2 + 1e-6)
    np.testing.assert_array_equal(rec.acc, content.acc_g.astype(np.float32))
    # time: from 0, monotone, at the rate (sample offsets are whole ns, pages at ms stamps)
    assert rec.t_s[0] == 0 and np.all(np.diff(rec.t_s) > 0)
    np.testing.assert_allclose(rec.t_s, np.arange(n) / rate_hz, atol=1e-6)
    assert float(rec.meta["start_unix_s"]) == pytest.approx(start, abs=1e-6)
    # temperature: one a page at the page time, interpolated to every sample
    np.testing.assert_allclose(content.page_t_s, np.arange(3) * SAMPLES_PER_PAGE / rate_hz)
    expected = np.interp(rec.t_s, content.page_t_s, temps)
    np.testing.assert_allclose(rec.temp_c, expected, atol=1e-4)


def test_truncated_geneactiv_file_is_an_input_error(tmp_path):
    raw = (DATA / "geneactiv_synthetic.bin").read_bytes()
    lines = raw.split(b"\r\n")
    last_hex = len(raw) - len(lines[-2]) - 2  # where the last page's hex line starts
    for name, size in [("mid.bin", last_hex + 7 * HEX_PER_SAMPLE + 5),  # inside a sample
                       ("whole.bin", last_hex + 100 * HEX_PER_SAMPLE),  # on a sample edge: still a cut page
                       ("pagehead.bin", last_hex - 30),  # inside the last page's header lines
                       ("head.bin", 400)]:  # inside the file header
        cut = tmp_path / name
        cut.write_bytes(raw[:size])
        with pytest.raises(InputError, match=name) as exc:
            selfcal.read(cut)
        if name != "head.bin":  # actfast alone drops a cut hex line silently; selfcal says so
            assert "truncated" in str(exc.value)


def test_geneactiv_file_through_the_cli_calibrate_exits_0_or_1(tmp_path):
    out = tmp_path / "cal.json"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-m", "selfcal.cli", "calibrate", str(DATA / "geneactiv_synthetic.bin"),
                        "--out", str(out)], capture_output=True, text=True, env=env, timeout=120)
    assert p.returncode in (0, 1), p.stderr  # calibrated, or a typed refusal
    assert "Traceback" not in p.stderr, p.stderr
    assert out.exists() == (p.returncode == 0)

"""Device files (Axivity .cwa, ActiGraph .gt3x) through actfast: read, calibrate, corrupt copies refused."""

from pathlib import Path

import numpy as np
import pytest

import selfcal
from selfcal.errors import InputError

pytest.importorskip("actfast")
DATA = Path(__file__).resolve().parents[1] / "data" / "device-formats"


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

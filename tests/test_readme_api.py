"""The README's Python example runs as written, and ``selfcal.__all__`` is exactly the public API."""

import re
import runpy
from pathlib import Path

import selfcal

ROOT = Path(__file__).resolve().parents[1]


def test_public_api_is_exactly_six_names():
    assert sorted(selfcal.__all__) == sorted(
        ["read", "calibrate", "Calibration", "load_calibration", "OnlineCalibrator", "diagnose"])
    for name in selfcal.__all__:
        assert getattr(selfcal, name).__doc__


def test_readme_python_example_runs(tmp_path, monkeypatch, capsys):
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    m = re.search(r"<!-- api-example:begin -->\s*```python\n(.*?)```\s*<!-- api-example:end -->", text, re.S)
    assert m, "README has no api-example block"
    script = tmp_path / "example.py"
    script.write_text(m.group(1))
    monkeypatch.chdir(ROOT)
    runpy.run_path(str(script), run_name="__main__")
    out = capsys.readouterr().out
    assert "calibrated" in out and "uncalibrated" in out and "median |a| = 1.000" in out


def test_calibration_round_trip_and_version_check(tmp_path):
    import pytest

    from selfcal.errors import InputError

    cal = selfcal.calibrate(ROOT / "data" / "ggir-wrist-84h" / "poses.csv", model="affine9+temperature_bias",
                            fixed_model=True)
    p = cal.save(tmp_path / "c.json")
    again = selfcal.load_calibration(p)
    assert again == cal and again.model == "affine9+temperature_bias"
    d = again.to_dict()
    d["format_version"] = 99
    with pytest.raises(InputError, match="format_version"):
        selfcal.Calibration.from_json(d)

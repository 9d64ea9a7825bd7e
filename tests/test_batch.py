"""Many files at once: one process per file, a summary row each, a bad file never stops the run."""

import csv
import shutil
from pathlib import Path

import pytest

from selfcal.cli import main

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.mark.parametrize("jobs", [1, 2])
def test_many_files_summary_and_error_rows(tmp_path, capsys, jobs):
    good = tmp_path / "wrist.csv"
    shutil.copy(DATA / "ggir-wrist-84h" / "poses.csv", good)
    text = (DATA / "ggir-wrist-84h" / "poses.csv").read_text()
    cut = tmp_path / "cut.csv"
    cut.write_text(text[: len(text) // 2].rsplit(",", 1)[0])  # truncated in the middle of a row
    junk = tmp_path / "junk.cwa"
    junk.write_bytes(b"\x00garbage" * 64)
    files = [good, cut, junk]
    if jobs == 2:
        pytest.importorskip("actfast")
        files.append(DATA / "device-formats" / "axivity_ax3.cwa")  # real, but 36 s: refused
        for real in ("axivity_ax3.cwa", "actigraph.gt3x", "geneactiv_synthetic.bin"):  # truncated copies: error rows
            raw = (DATA / "device-formats" / real).read_bytes()
            cut_copy = tmp_path / f"cut_{real}"
            cut_copy.write_bytes(raw[: len(raw) * 6 // 10 + 7])
            files.append(cut_copy)
    summary = tmp_path / "summary.csv"
    code = main(["calibrate", *map(str, files), "--jobs", str(jobs), "--summary", str(summary)])
    out = capsys.readouterr()
    rows = list(csv.DictReader(summary.open()))
    assert [Path(r["file"]).name for r in rows] == [Path(f).name for f in files]
    by = {Path(r["file"]).name: r for r in rows}
    assert by["wrist.csv"]["status"] in ("calibrated", "provisional")
    assert float(by["wrist.csv"]["residual_after_mg"]) < float(by["wrist.csv"]["residual_before_mg"])
    assert Path(by["wrist.csv"]["calibration"]).exists()
    assert by["cut.csv"]["status"] == "error" and "cut.csv" in by["cut.csv"]["error"]
    assert by["junk.cwa"]["status"] == "error" and "junk.cwa" in by["junk.cwa"]["error"]
    if jobs == 2:
        assert by["cut_axivity_ax3.cwa"]["status"] == "error" and "truncated" in by["cut_axivity_ax3.cwa"]["error"]
        assert by["cut_actigraph.gt3x"]["status"] == "error" and "cut_actigraph.gt3x" in by["cut_actigraph.gt3x"]["error"]
        cut_bin = by["cut_geneactiv_synthetic.bin"]
        assert cut_bin["status"] == "error" and "truncated" in cut_bin["error"]
    failed = sum(r["status"] in ("error", "uncalibrated") for r in rows)
    assert code == failed == len(files) - 1  # the exit code is the number of files that failed
    md = summary.with_suffix(".md").read_text()
    assert "wrist.csv" in md and "error" in md
    assert summary.with_suffix(".png").exists()
    assert f"1 of {len(files)} files calibrated" in out.err


def test_many_files_refuses_single_file_options(tmp_path, capsys):
    code = main(["calibrate", str(DATA / "ggir-wrist-84h" / "poses.csv"), str(DATA / "ggir-wrist-84h" / "poses.csv"),
                 "--out", str(tmp_path / "x.json")])
    assert code == 2 and "--out-dir" in capsys.readouterr().err

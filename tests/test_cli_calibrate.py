"""`selfcal calibrate` / `selfcal apply` on real recordings and on bad input."""

import json
from pathlib import Path

import numpy as np
import pytest

from selfcal.cli import main
from selfcal.io import read_recording

DATA = Path(__file__).resolve().parents[1] / "data"  # real recordings shipped with the repository


def run_json(capsys, *argv):
    code = main(list(argv))
    out = capsys.readouterr()
    return code, (json.loads(out.out) if out.out.strip().startswith("{") else None), out.err


def test_imutk_raw_counts_residual_below_0_6_mg(capsys):
    code, cal, _ = run_json(capsys, "calibrate", str(DATA / "imutk-xsens-multipose/samples.csv"), "--json")
    assert code == 0
    assert cal["unit"] == "counts" and cal["status"] == "calibrated"
    assert cal["residual_rms_mg"] < 0.6
    # the model maps counts to g: a still window's calibrated norm is 1 g
    rec = read_recording(DATA / "imutk-xsens-multipose/samples.csv")
    m, o = np.array(cal["matrix"]), np.array(cal["offset"])
    first_second = rec.acc[:100].mean(axis=0)  # the recording starts with ~50 s still
    assert abs(np.linalg.norm(m @ (first_second - o)) - 1) < 2e-3


@pytest.mark.parametrize("model", ["scale6", "affine9"])
def test_nilspod_agrees_with_six_face_within_uncertainty(capsys, model):
    path = DATA / "imucal-nilspod-ferraris/samples.csv"
    code, cal, _ = run_json(capsys, "calibrate", str(path), "--json", "--model", model)
    assert code == 0 and cal["unit"] == "mps2"
    rec = read_recording(path)
    sec = json.loads((DATA / "imucal-nilspod-ferraris/sections.json").read_text())
    for i, ax in enumerate("xyz"):
        p = rec.acc[sec[f"{ax}_p"]["start"]: sec[f"{ax}_p"]["end"]]
        a = rec.acc[sec[f"{ax}_a"]["start"]: sec[f"{ax}_a"]["end"]]
        bias = (p[:, i].mean() + a[:, i].mean()) / 2
        scale = 1.0 / ((p[:, i].mean() - a[:, i].mean()) / 2)  # g per m/s^2
        bias_sd = 0.5 * np.hypot(p[:, i].std(ddof=1) / np.sqrt(len(p)), a[:, i].std(ddof=1) / np.sqrt(len(a)))
        scale_sd = scale**2 * bias_sd  # same propagation for the half-difference
        b, sb = cal["params"][f"b{ax}"], cal["std"][f"b{ax}"]
        s, ss = cal["params"][f"s{ax}"], cal["std"][f"s{ax}"]
        assert abs(b - bias) < 2 * np.hypot(sb, bias_sd), (ax, b, bias, sb, bias_sd)
        assert abs(s - scale) < 2 * np.hypot(ss, scale_sd), (ax, s, scale, ss, scale_sd)


def test_apply_writes_calibrated_g(tmp_path, capsys):
    src = DATA / "imutk-xsens-multipose/samples.csv"
    cal_path = tmp_path / "cal.json"
    assert main(["calibrate", str(src), "--out", str(cal_path)]) == 0
    out = tmp_path / "cal.csv"
    assert main(["apply", str(src), "--calibration", str(cal_path), "--out", str(out)]) == 0
    rec = read_recording(out)
    assert rec.unit == "g"
    still = np.linalg.norm(rec.acc[:3000], axis=1)  # initial still part
    assert abs(np.median(still) - 1) < 1e-3
    capsys.readouterr()


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


HEAD = "# selfcal-recording v1\n# kind={kind}\n"


def _stream(rows):
    return "\n".join(",".join(f"{v:.6f}" for v in r) for r in rows) + "\n"


@pytest.mark.parametrize(
    "name,text,expect",
    [
        ("nan.csv", HEAD.format(kind="samples") + "t_s,ax_g,ay_g,az_g\n0,0,0,1\n0.05,nan,0,1\n", "nan"),
        ("inf.csv", HEAD.format(kind="samples") + "t_s,ax_g,ay_g,az_g\n0,0,0,1\n0.05,0,inf,1\n", "inf"),
        ("ragged.csv", HEAD.format(kind="samples") + "t_s,ax_g,ay_g,az_g\n0,0,0,1\n0.05,0,1\n", ":4:"),
        ("units.csv", HEAD.format(kind="samples") + "t_s,ax_g,ay_mps2,az_g\n0,0,0,1\n", "unit"),
        ("units2.csv", HEAD.format(kind="samples") + "t_s,ax_furlong,ay_furlong,az_furlong\n0,0,0,1\n", "ax"),
    ],
)
def test_bad_files_exit_2_with_a_named_reason(tmp_path, capsys, name, text, expect):
    code = main(["calibrate", _write(tmp_path, name, text)])
    err = capsys.readouterr().err
    assert code == 2
    assert expect.lower() in err.lower(), err
    assert name in err


def test_single_still_pose_is_not_a_silent_identity(tmp_path, capsys):
    rng = np.random.default_rng(0)
    t = np.arange(400) / 20
    acc = np.array([0.01, -0.02, 1.03]) + rng.normal(0, 0.002, (400, 3))
    path = _write(tmp_path, "one.csv", HEAD.format(kind="samples") + "t_s,ax_g,ay_g,az_g\n" + _stream(np.c_[t, acc]))
    code = main(["calibrate", path, "--json"])
    out = capsys.readouterr()
    assert code == 1  # refused: nothing could be published (exit codes: README)
    assert "insufficient_coverage" in out.err
    assert json.loads(out.out)["calibration"] is None


def test_identical_poses_table(tmp_path, capsys):
    rows = [[i * 10, 0.01, 0.02, 1.01, 0.002, 0.002, 0.002, 10] for i in range(30)]
    text = HEAD.format(kind="poses") + "t_s,ax_g,ay_g,az_g,sdx_g,sdy_g,sdz_g,duration_s\n" + _stream(rows)
    code = main(["calibrate", _write(tmp_path, "same.csv", text)])
    assert code == 1  # refused
    assert "insufficient_coverage" in capsys.readouterr().err


def test_raw_counts_with_no_still_window(tmp_path, capsys):
    rng = np.random.default_rng(1)
    t = np.arange(2000) / 100
    acc = 32768 + rng.normal(0, 3000, (2000, 3))  # only motion
    text = HEAD.format(kind="samples") + "t_s,ax_counts,ay_counts,az_counts\n" + _stream(np.c_[t, acc])
    code = main(["calibrate", _write(tmp_path, "moving.csv", text)])
    err = capsys.readouterr().err
    assert code == 2 and "no still window" in err


def test_apply_refuses_a_calibration_in_another_unit(tmp_path, capsys):
    cal = {"model": "affine9", "unit": "counts", "params": {n: v for n, v in zip(
        ["bx", "by", "bz", "sx", "sy", "sz", "nxy", "nxz", "nyz"], [0, 0, 0, 1, 1, 1, 0, 0, 0])}}
    cp = _write(tmp_path, "cal.json", json.dumps(cal))
    rec = _write(tmp_path, "g.csv", HEAD.format(kind="samples") + "t_s,ax_g,ay_g,az_g\n0,0,0,1\n")
    code = main(["apply", rec, "--calibration", cp, "--out", str(tmp_path / "o.csv")])
    assert code == 2 and "calibrate" in capsys.readouterr().err
    bad = _write(tmp_path, "bad.json", json.dumps({"model": "affine9", "unit": "g"}))
    code = main(["apply", rec, "--calibration", bad, "--out", str(tmp_path / "o.csv")])
    assert code == 2 and "params" in capsys.readouterr().err

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


def test_raw_counts_of_a_device_that_stays_near_one_orientation_calibrate():
    """An insole's axes never turn through +-1 g: the counts' percentile spread gave 1.5
    counts/g for 256, no still window passed the detector, and a counts file of such a
    device never calibrated. The signed median norm finds the windows; when their means
    determine a sphere (here they do: 8 degrees of tilt) its radius is the scale."""
    from selfcal.config import load_config
    from selfcal.io import Recording
    from selfcal.pipeline import calibrate_recording

    rng = np.random.default_rng(5)
    parts = []
    for _ in range(120):  # 10-s still poses within ~8 degrees of flat, 2 s of motion between
        d = np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.07, 3)
        d /= np.linalg.norm(d)
        parts += [np.tile(d, (200, 1)) + rng.normal(0, 0.002, (200, 3)), d + rng.normal(0, 0.3, (40, 3))]
    acc_g = np.vstack(parts)
    t = np.arange(len(acc_g)) / 20.0
    counts = Recording(kind="samples", unit="counts", t_s=t, acc=np.round(acc_g * 256.0 + [3, -2, 5]))
    run = calibrate_recording(counts, config=load_config())
    assert run.n_windows > 100 and run.calibration is not None
    assert "254." in run.notes[0] or "255." in run.notes[0] or "256." in run.notes[0], run.notes  # counts per g
    probe = np.array([[0.0, 0.0, 256.0]])
    from selfcal.models import ErrorModel

    m = ErrorModel(run.calibration["model"])
    a = m.apply(m.from_dict(run.calibration["params"]), probe, np.full(1, 25.0), np.zeros(1))
    assert abs(np.linalg.norm(a) - 1.0) < 0.02  # flat: 1 g within 2 %


def test_raw_counts_of_an_insole_that_stays_flat_calibrate(tmp_path):
    """A simulated insole's stream in g and in counts (256 a g) give the same calibrated
    specific force."""
    from selfcal.config import load_config, section
    from selfcal.io import Recording
    from selfcal.pipeline import calibrate_recording
    from selfcal.sim import SimConfig, Simulation

    cfg = load_config()
    sim = Simulation(SimConfig.from_section(section(cfg, "sim")), np.random.default_rng(7), days=0.4, seed=7)
    ch = sim.samples()
    in_g = Recording(kind="samples", unit="g", t_s=ch.t_s, acc=ch.acc_g, temp_c=ch.temp_c)
    counts = Recording(kind="samples", unit="counts", t_s=ch.t_s, acc=ch.acc_g * 256.0, temp_c=ch.temp_c)
    g_run, c_run = calibrate_recording(in_g, config=cfg), calibrate_recording(counts, config=cfg)
    assert c_run.calibration is not None and g_run.calibration is not None
    assert c_run.n_windows == g_run.n_windows
    from selfcal.models import ErrorModel

    probe = np.array([[0.0, 0.0, 1.0], [0.3, -0.2, 0.93]])
    a = [ErrorModel(r.calibration["model"]).apply(
        ErrorModel(r.calibration["model"]).from_dict(r.calibration["params"]), probe * k, np.full(2, 25.0),
        np.zeros(2)) for r, k in ((g_run, 1.0), (c_run, 256.0))]
    np.testing.assert_allclose(a[1], a[0], atol=2e-3)  # within 2 mg


def test_still_windows_of_one_orientation_keep_the_rough_counts_scale():
    from selfcal.fit import Normalizer
    from selfcal.pipeline import _counts_normalizer

    rng = np.random.default_rng(2)
    means = np.array([0.0, 0.0, 256.0]) + rng.normal(0, 0.5, (50, 3))  # one orientation, counts
    rough = Normalizer((0.0, 0.0, 0.0), 256.3)
    got, note = _counts_normalizer(means, rough)
    assert got is rough and "do not determine a sphere" in note
    tilted = np.array([[np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)] for a, b in
                       rng.uniform([0, 0], [np.pi, 2 * np.pi], (50, 2))]) * 255.0 + [4.0, -2.0, 1.0]
    got, note = _counts_normalizer(tilted, rough)
    assert abs(got.scale - 255.0) < 0.5 and "sphere fit" in note


def test_a_poses_table_taken_at_a_slow_rate_calibrates(tmp_path, capsys):
    """The detector never runs on a poses table (its rate gives the windows' durations): the
    detector's check of the rate against max_gap_s refused a 4 Hz table that calibrated before."""
    from selfcal.cli import main

    out = tmp_path / "p4.csv"
    assert main(["simulate", "--days", "0.5", "--seed", "1", "--out", str(out), "--rate-hz", "4", "--kind", "poses"]) == 0
    capsys.readouterr()
    assert main(["calibrate", str(out), "--json"]) in (0, 1)  # (1: refused for the data, not for the rate)
    captured = capsys.readouterr()
    assert "max_gap_s" not in captured.err and captured.out.startswith("{")

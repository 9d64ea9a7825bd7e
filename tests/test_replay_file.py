"""``selfcal replay --recording FILE``: a recorded file through the online calibrator, scored against its truth.

* The file is streamed in blocks exactly as ``selfcal calibrate`` streams it: it is never
  read whole, and it publishes the same versions as ``calibrate --history``.
* With the truth ``selfcal simulate --out FILE`` wrote beside it, every version is scored
  as ``bench/consistency.py`` scores it (the same numbers), and the final true error
  agrees with one computed here from the matrices alone.
* Without a truth it reports the history only and says so; bad input gives the
  documented exit codes (2 usage or input error, 1 nothing published) and one line.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from selfcal.cli import main
from selfcal.fit import sphere_directions

BENCH = Path(__file__).resolve().parents[1] / "bench"
POSES_SEED, POSES_DAYS = 7, 3  # reaches 'calibrated' within the 3 days: the consistency figures are not empty


def cli(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    d = tmp_path_factory.mktemp("replay-file")
    poses, samples = d / "poses.csv", d / "samples.csv"
    assert main(["simulate", "--days", str(POSES_DAYS), "--seed", str(POSES_SEED), "--kind", "poses",
                 "--effects", "none", "--out", str(poses)]) == 0
    assert main(["simulate", "--days", "1", "--seed", "3", "--kind", "samples", "--effects", "none",
                 "--out", str(samples)]) == 0
    assert (d / "poses.truth.json").exists() and (d / "samples.truth.json").exists()
    return d


def _history(path: Path) -> list[dict]:
    rows = [json.loads(line) for line in path.read_text().splitlines()]
    for r in rows:
        r["fit"].pop("fit_ms", None)  # a wall-clock time, the one field that differs between runs
    return rows


def _bench():
    sys.path.insert(0, str(BENCH))
    try:
        import consistency
    finally:
        sys.path.remove(str(BENCH))
    return consistency


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == pytest.approx(b, rel=1e-12)
    return a == b


def _true_sphere_mg(version: dict, truth: dict) -> float:
    """True whole-sphere error of an affine9 version from the matrices alone (no effects in the truth)."""
    d = sphere_directions(2000)
    m_true, o_true = np.asarray(truth["matrix"]), np.asarray(truth["offset"])
    raw = o_true + d @ np.linalg.inv(m_true).T  # raw = offset + inv(matrix) a_true
    a = (raw - np.asarray(version["offset"])) @ np.asarray(version["matrix"]).T
    return float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - 1) ** 2)) * 1e3)


def test_poses_recording_scored_as_the_bench_scores_it(sims, tmp_path, capsys):
    rec = sims / "poses.csv"
    code, out, _ = cli(capsys, "replay", "--recording", rec, "--json", "--no-progress", "--history", tmp_path / "h.jsonl")
    assert code == 0
    got = json.loads(out)
    assert got["truth"] == str(sims / "poses.truth.json") and got["model"] == "affine9"
    rows, s = got["versions"], got["summary"]
    assert len(rows) == s["versions"] >= 3
    for r in rows:
        assert np.isfinite(r["true_mg"]) and r["true_mg"] > 0 and np.isfinite(r["predicted_mg"])
        assert np.all(np.isfinite(r["z"])) and len(r["z"]) == 9
    assert s["final_true_mg"] < 0.1 * rows[0]["true_mg"]  # it learns
    assert s["calibrated_versions"] >= 1 and s["first_calibrated_h"] <= POSES_DAYS * 24
    assert s["versions_per_week"] == pytest.approx(len(rows) / (POSES_DAYS / 7))
    assert np.isfinite(s["crlb_sphere_mg"]) and s["final_target_mg"] >= 0.5 and s["final_ok"] is True
    assert 0 <= s["within_2sd"] <= 1 and s["sphere_ratio_ok"] is not None and s["jumps"] <= s["pairs"]

    # the final error, from the matrices alone
    truth = json.loads((sims / "poses.truth.json").read_text())
    final = _history(tmp_path / "h.jsonl")[-1]
    assert final["version"] == rows[-1]["version"]
    assert s["final_true_mg"] == pytest.approx(_true_sphere_mg(final, truth), rel=1e-6)

    # bench/consistency.py on the same simulation (same seed and days): the same scores
    consistency = _bench()
    bench_dir = tmp_path / "bench"
    bench_dir.mkdir()
    with capsys.disabled():
        run = consistency.run_one({"seed": POSES_SEED, "days": POSES_DAYS, "effect": "none", "model": "affine9",
                                   "tmp": str(bench_dir)})
    capsys.readouterr()
    assert run["exit_code"] == 0 and len(run["versions"]) == len(rows)
    for a, b in zip(run["versions"], rows):
        assert (a["version"], a["t_s"], a["status"]) == (b["version"], b["t_s"], b["status"])
        assert a["true_mg"] == pytest.approx(b["true_mg"], rel=1e-12)
        assert a["predicted_mg"] == pytest.approx(b["predicted_mg"], rel=1e-12)
        np.testing.assert_allclose(a["z"], b["z"], rtol=1e-12, atol=1e-12)
    # replay --recording has the recording alone: its CRLB uses the noise model; the bench re-runs
    # the simulator and uses each window's true noise for its target (and an efficient oracle)
    assert run["crlb_model_noise_mg"] == pytest.approx(s["crlb_sphere_mg"], rel=1e-12)
    assert np.isfinite(run["crlb_sphere_mg"]) and np.isfinite(run["oracle_final_mg"])
    bench = consistency.score([run])
    seed_row = bench["per_seed"][0]
    for k in ("versions", "versions_per_week", "calibrated_versions", "first_calibrated_h", "final_status",
              "final_true_mg", "final_predicted_mg"):
        assert _same(seed_row[k], s[k]), (k, seed_row[k], s[k])
    for k in ("within_2sd", "max_abs_z", "sphere_ratio_ok", "jumps", "pairs"):
        assert _same(bench[k], s[k]), (k, bench[k], s[k])


@pytest.mark.parametrize("kind", ["poses", "samples"])
def test_same_versions_as_calibrate_history(sims, tmp_path, capsys, kind):
    rec = sims / f"{kind}.csv"
    assert cli(capsys, "calibrate", rec, "--history", tmp_path / "cal.jsonl", "--json")[0] == 0
    code, out, _ = cli(capsys, "replay", "--recording", rec, "--history", tmp_path / "replay.jsonl", "--json",
                       "--no-progress")
    assert code == 0
    history = _history(tmp_path / "cal.jsonl")
    assert history == _history(tmp_path / "replay.jsonl")
    rows = json.loads(out)["versions"]
    assert [(r["version"], r["t_s"], r["status"], r["predicted_mg"], r["params"], r["std"]) for r in rows] == [
        (c["version"], c["t_s"], c["status"], c["predicted_sphere_rms_mg"], c["params"], c["std"]) for c in history]
    assert all(np.isfinite(r["true_mg"]) for r in rows)


def test_samples_file_streams_in_blocks_with_progress_by_bytes(sims, capsys, monkeypatch):
    """Never read whole (memory bounded by the block, not the file), progress on a terminal's stderr."""
    import selfcal.io

    def whole(*a, **k):
        raise AssertionError("read_recording: the file was read whole")

    real_iter = selfcal.io.iter_recording
    sizes: list[int] = []

    def counting_iter(*a, **k):
        for block in real_iter(*a, **k):
            sizes.append(len(block))
            yield block

    monkeypatch.setattr(selfcal.io, "read_recording", whole)
    monkeypatch.setattr(selfcal.io, "iter_recording", counting_iter)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    code, out, err = cli(capsys, "replay", "--recording", sims / "samples.csv")
    assert code == 0
    assert len(sizes) > 10 and max(sizes) <= 100_000
    assert "calibrate" in err and "B/s" in err  # tqdm by bytes
    assert "truth: " in out and "final: true" in out and "CRLB" not in out  # a samples table has no window table
    sizes.clear()
    code, _, err = cli(capsys, "replay", "--recording", sims / "samples.csv", "--no-progress", "--json")
    assert code == 0 and err == ""


def test_without_truth_the_history_only(sims, tmp_path, capsys):
    rec = tmp_path / "copy.csv"
    shutil.copy(sims / "poses.csv", rec)
    code, out, err = cli(capsys, "replay", "--recording", rec, "--no-progress")
    assert code == 0, err
    assert "no truth found" in out and "copy.truth.json" in out and "true mg" not in out
    code, out, _ = cli(capsys, "replay", "--recording", rec, "--no-progress", "--json")
    got = json.loads(out)
    assert code == 0 and got["truth"] is None and any("no truth found" in n for n in got["notes"])
    assert got["versions"] and all("true_mg" not in r for r in got["versions"])
    assert got["summary"]["final_true_mg"] is None and got["summary"]["final_predicted_mg"] > 0
    # an explicit --truth scores it (and notes that the truth was written for another file name)
    code, out, _ = cli(capsys, "replay", "--recording", rec, "--truth", sims / "poses.truth.json", "--json",
                       "--no-progress")
    got = json.loads(out)
    assert code == 0 and got["summary"]["final_true_mg"] > 0 and any("poses.csv" in n for n in got["notes"])


BAD = [
    ("missing recording", lambda d, t: ["--recording", t / "nope.csv"], 2, "no such file"),
    ("recording is a folder", lambda d, t: ["--recording", t], 2, "directory"),
    ("binary recording", lambda d, t: ["--recording", t / "binary.csv"], 2, "not UTF-8"),
    ("no magic line", lambda d, t: ["--recording", t / "nomagic.csv"], 2, "selfcal-recording"),
    ("missing --truth", lambda d, t: ["--recording", d / "poses.csv", "--truth", t / "no.json"], 2, "no such truth file"),
    ("truth not JSON", lambda d, t: ["--recording", d / "poses.csv", "--truth", d / "poses.csv"], 2, "not JSON"),
    ("truth of another kind", lambda d, t: ["--recording", d / "poses.csv", "--truth", t / "other.json"], 2,
     "not a selfcal truth file"),
    ("with a simulation option", lambda d, t: ["--recording", d / "poses.csv", "--seed", "0"], 2, "do not apply"),
    ("--truth without --recording", lambda d, t: ["--truth", d / "poses.truth.json"], 2, "takes --recording"),
    ("history into a missing folder", lambda d, t: ["--recording", d / "poses.csv", "--history", t / "no" / "h.jsonl"],
     2, "does not exist"),
    ("unknown model", lambda d, t: ["--recording", d / "poses.csv", "--model", "affine12"], 2, "unknown base model"),
    ("nothing published", lambda d, t: ["--recording", t / "few.csv"], 1, "no calibration published"),
]


@pytest.mark.parametrize("name,argv,code,needle", BAD, ids=[b[0] for b in BAD])
def test_bad_input(sims, tmp_path, capsys, name, argv, code, needle):
    (tmp_path / "binary.csv").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "nomagic.csv").write_text("t_s,ax_g,ay_g,az_g\n0,0,0,1\n")
    (tmp_path / "other.json").write_text('{"format": "selfcal-calibration"}')
    lines = (sims / "poses.csv").read_text().splitlines()
    header = [ln for ln in lines if ln.startswith("#")] + [lines[sum(ln.startswith("#") for ln in lines)]]
    (tmp_path / "few.csv").write_text("\n".join(header + lines[len(header):len(header) + 3]) + "\n")
    got, out, err = cli(capsys, "replay", *argv(sims, tmp_path), "--no-progress")
    assert got == code, (got, err)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert needle.lower() in lines[0].lower(), lines[0]
    assert lines[0].startswith("selfcal replay: ")

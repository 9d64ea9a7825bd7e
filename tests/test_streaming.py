"""Streaming a recording in blocks gives exactly what reading it whole gives.

A 20 Hz samples file of several blocks, with a still bout cut by a block edge: the same
still poses and the same calibration (to 1e-9) whether the file is read whole or in
blocks; malformed rows are reported with their own line numbers, also in the last
block and across a block edge.
"""

import numpy as np
import pytest

from posegen import random_truth, sample_stream, spread_directions
from selfcal.config import load_config
from selfcal.errors import InputError
from selfcal.io import Recording, iter_recording, read_recording, write_recording
from selfcal.models import ErrorModel
from selfcal.pipeline import calibrate_path, calibrate_recording

A9 = ErrorModel("affine9")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    rng = np.random.default_rng(71)
    truth = random_truth(rng)
    t, raw, _ = sample_stream(rng, A9, truth, spread_directions(rng, 40), still_s=30.0)
    temp = 25 + 0.01 * np.arange(len(t)) / 20
    path = tmp_path_factory.mktemp("stream") / "rec.csv"
    write_recording(path, Recording(kind="samples", unit="g", t_s=t, acc=raw, temp_c=temp))
    return path, t


def test_blocks_concatenate_to_the_whole_file(recording):
    path, t = recording
    whole = read_recording(path)
    blocks = list(iter_recording(path, block_rows=7001))
    assert len(blocks) > 3
    np.testing.assert_array_equal(np.concatenate([b.t_s for b in blocks]), whole.t_s)
    np.testing.assert_array_equal(np.concatenate([b.acc for b in blocks]), whole.acc)
    np.testing.assert_array_equal(np.concatenate([b.temp_c for b in blocks]), whole.temp_c)


def test_streamed_calibration_equals_whole_file(recording):
    path, t = recording
    block = 7001
    # a still bout is cut by a block edge: sample 7001 falls inside a 30-s still
    still = 30 * 20
    cycle = still + int(1.5 * 20)
    assert 0 < block % cycle < still
    cfg = load_config(None)
    whole = calibrate_recording(read_recording(path), "affine9", cfg)
    streamed = calibrate_path(path, "affine9", cfg, block_rows=block)
    a, b = whole.calibrator.store, streamed.calibrator.store
    assert a.n_seen == b.n_seen > 30
    ia, ib = np.argsort(a.key), np.argsort(b.key)
    np.testing.assert_array_equal(a.key[ia], b.key[ib])
    np.testing.assert_allclose(a.stats[ia], b.stats[ib], rtol=1e-9, atol=1e-12)
    pa = A9.from_dict(whole.calibration["params"])
    pb = A9.from_dict(streamed.calibration["params"])
    np.testing.assert_allclose(pa, pb, rtol=1e-9, atol=1e-12)
    assert whole.calibration["version"] == streamed.calibration["version"]


def test_errors_keep_their_line_numbers_in_the_last_block_and_across_an_edge(recording, tmp_path):
    path, _ = recording
    lines = path.read_text().splitlines()
    header = next(i for i, x in enumerate(lines) if x.startswith("t_s"))
    bad = list(lines)
    bad[-2] = bad[-2] + ",9"  # ragged row in the last block
    p1 = tmp_path / "ragged.csv"
    p1.write_text("\n".join(bad) + "\n")
    with pytest.raises(InputError, match=rf"ragged.csv:{len(lines) - 1}:"):
        list(iter_recording(p1, block_rows=5000))
    edge = header + 1 + 5000  # first line of the second block
    back = list(lines)
    t_prev = float(back[edge - 1].split(",")[0])
    back[edge] = ",".join([repr(t_prev - 1.0)] + back[edge].split(",")[1:])
    p2 = tmp_path / "back.csv"
    p2.write_text("\n".join(back) + "\n")
    with pytest.raises(InputError, match=rf"back.csv:{edge + 1}:1: .*t_s decreases"):
        list(iter_recording(p2, block_rows=5000))


def test_clean_blocks_take_the_fast_parser_and_agree_with_the_exact_one(recording, monkeypatch):
    pytest.importorskip("pyarrow")
    import selfcal.io as io_mod

    path, _ = recording
    exact = list(iter_recording(path, block_rows=9000))
    calls = {"fast": 0}
    orig = io_mod._FastBlocks.parse

    def spy(self, *a, **k):
        out = orig(self, *a, **k)
        calls["fast"] += out is not None
        return out

    monkeypatch.setattr(io_mod._FastBlocks, "parse", spy)
    fast = list(iter_recording(path, block_rows=9000))
    assert calls["fast"] == len(fast) > 2
    monkeypatch.setattr(io_mod._FastBlocks, "parse", lambda self, *a, **k: None)
    slow = list(iter_recording(path, block_rows=9000))
    for a, b in zip(fast, slow):
        np.testing.assert_array_equal(a.t_s, b.t_s)
        np.testing.assert_array_equal(a.acc, b.acc)
        np.testing.assert_array_equal(a.temp_c, b.temp_c)
    assert len(exact) == len(fast)


def test_plain_csv_with_columns(tmp_path, capsys):
    from selfcal.cli import main
    from selfcal.io import plain_columns

    rng = np.random.default_rng(72)
    truth = random_truth(rng)
    t, raw, _ = sample_stream(rng, A9, truth, spread_directions(rng, 30))
    body = "\n".join(f"{a:.4f},{b:.6f},{c:.6f},{d:.6f}" for a, (b, c, d) in zip(t, raw))
    with_header = tmp_path / "h.csv"
    with_header.write_text("time,x,y,z\n" + body + "\n")
    bare = tmp_path / "b.csv"
    bare.write_text(body + "\n")
    cols = plain_columns("t,x,y,z", "g")
    assert cols == ["t_s", "ax_g", "ay_g", "az_g"]
    with pytest.raises(InputError, match=r"--columns t,x,y,w: no column for z"):  # (was: the file's line 3)
        plain_columns("t,x,y,w", "g")
    a = np.concatenate([r.acc for r in iter_recording(with_header, 500, columns=cols)])
    b = np.concatenate([r.acc for r in iter_recording(bare, 500, columns=cols)])
    np.testing.assert_array_equal(a, b)
    assert len(a) == len(t)
    assert main(["calibrate", str(with_header), "--columns", "t_s,ax_g,ay_g,az_g", "--json"]) == 0
    capsys.readouterr()
    # a bad cell is reported at the file's own line (header = line 1, so row k is line k + 1)
    lines = with_header.read_text().splitlines()
    lines[100] = lines[100].replace(",", ",x", 1)
    broken = tmp_path / "broken.csv"
    broken.write_text("\n".join(lines) + "\n")
    assert main(["calibrate", str(broken), "--columns", "t,x,y,z", "--unit", "g"]) == 2
    assert "broken.csv:101:" in capsys.readouterr().err
    # bare axis names without a unit: one line that says what is missing
    assert main(["calibrate", str(bare), "--columns", "t,x,y,z"]) == 2
    assert "--unit" in capsys.readouterr().err


def test_apply_streams_blocks_and_equals_the_whole_file(recording, tmp_path, monkeypatch, capsys):
    """``selfcal apply`` writes block by block; the file equals the model applied to the
    whole recording, and the median |a| it prints is the rows' median to 1e-6 g."""
    import functools
    import json

    import selfcal.commands.apply as apply_cmd
    from selfcal.cli import main

    path, _ = recording
    theta = A9.nominal()
    theta[:3] = [0.01, -0.02, 0.015]
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"model": "affine9", "unit": "g", "params": A9.to_dict(theta)}))
    monkeypatch.setattr(apply_cmd, "iter_recording", functools.partial(iter_recording, block_rows=6007))
    out = tmp_path / "out.csv"
    assert main(["apply", str(path), "--calibration", str(cal), "--out", str(out)]) == 0
    whole = read_recording(path)
    want = A9.apply(theta, whole.acc, whole.temp_c, whole.t_s)
    got = read_recording(out)
    assert got.unit == "g" and len(got) == len(whole) > 3 * 6007
    np.testing.assert_array_equal(got.t_s, whole.t_s)
    np.testing.assert_allclose(got.acc, want, rtol=0, atol=1e-15)
    median = float(capsys.readouterr().out.split("median |a| = ")[1].split()[0])
    assert abs(median - np.median(np.linalg.norm(want, axis=1))) <= 1e-5


def test_long_jobs_show_progress_by_bytes_read(recording, tmp_path, capsys, monkeypatch):
    """calibrate, diagnose's still windows and apply show a bar on stderr (apply and diagnose
    showed nothing: 30-40 s on three days of wear)."""
    import sys

    from selfcal.pipeline import ByteProgress, path_poses

    recording, _ = recording
    path_poses(recording, load_config(), block_rows=4000, progress=True)
    err = capsys.readouterr().err
    assert "still windows" in err and "100%" in err
    bar = ByteProgress(recording, "apply", False)  # not shown: nothing written
    bar(10**9)
    bar.close()
    assert capsys.readouterr().err == ""
    from selfcal.cli import main

    cal = tmp_path / "cal.json"
    assert main(["calibrate", str(recording), "--out", str(cal)]) == 0
    capsys.readouterr()
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert main(["apply", str(recording), "--calibration", str(cal), "--out", str(tmp_path / "o.csv")]) == 0
    err = capsys.readouterr().err
    assert "apply" in err and "100%" in err

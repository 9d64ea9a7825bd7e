"""Wrong invocations: each gives its documented exit code and one line on stderr, never a traceback.

Exit codes (README, ``selfcal --help``): 0 done, 1 refused or failed, 2 usage or input error.
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from selfcal.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
POSES = ROOT / "data" / "ggir-wrist-84h" / "poses.csv"


def run_cli(*args, cwd=None):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "selfcal.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, env=env, timeout=120)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    (d / "empty.csv").write_text("")
    (d / "binary.csv").write_bytes(bytes(range(256)) * 4)
    (d / "nomagic.csv").write_text("t_s,ax_g,ay_g,az_g\n0,0,0,1\n")
    (d / "bad.toml").write_text("[fit\nmax_iter = 3\n")
    (d / "unknown_key.toml").write_text("[fit]\nno_such_key = 3\n")
    (d / "bad_cal.json").write_text("{not json")
    (d / "garbage.cwa").write_bytes(b"not a CWA file " * 100)
    (d / "data.xyz").write_bytes(bytes(range(256)) * 4)
    (d / "adir").mkdir()
    (d / "latin1.toml").write_bytes("[fit]\n# caf\xe9\n".encode("latin-1"))
    (d / "section_value.toml").write_text("detector = 5\n")
    (d / "list_cal.json").write_text("[1, 2]")
    (d / "poses_copy.csv").write_bytes(POSES.read_bytes())
    ro = d / "readonly"
    ro.mkdir()
    ro.chmod(0o500)
    return d


CASES = [
    ("missing file", lambda d: ["calibrate", d / "nope.csv"], 2, "no such file"),
    ("directory as file", lambda d: ["calibrate", d / "adir"], 2, "directory"),
    ("unknown model", lambda d: ["calibrate", POSES, "--model", "affine12"], 2, "unknown base model"),
    ("unknown effect", lambda d: ["calibrate", POSES, "--model", "affine9+wobble"], 2, "unknown effect"),
    ("cross-axis terms on scale6", lambda d: ["calibrate", POSES, "--model", "scale6+temperature_cross"], 2,
     "cross-axis"),
    ("a bias step by name", lambda d: ["calibrate", POSES, "--model", "affine9+bias_step"], 2, "t_step_s"),
    ("worker nice out of range", lambda d: ["worker", "--db", "postgresql://x@127.0.0.1:1/x", "--nice", "25"], 2,
     "--nice 25"),
    ("worker threads out of range", lambda d: ["worker", "--db", "postgresql://x@127.0.0.1:1/x", "--threads", "0"], 2,
     "--threads 0"),
    ("bad TOML", lambda d: ["calibrate", POSES, "--config", d / "bad.toml"], 2, "invalid TOML"),
    ("missing config", lambda d: ["calibrate", POSES, "--config", d / "none.toml"], 2, "config file not found"),
    ("unknown config key", lambda d: ["calibrate", POSES, "--config", d / "unknown_key.toml"], 2, "no_such_key"),
    ("output in a missing folder", lambda d: ["calibrate", POSES, "--out", d / "no" / "cal.json"], 2, "does not exist"),
    ("output is a folder", lambda d: ["calibrate", POSES, "--out", d / "adir"], 2, "is a directory"),
    ("history in a missing folder", lambda d: ["calibrate", POSES, "--history", d / "no" / "h.jsonl"], 2, "does not exist"),
    ("corrupt device file", lambda d: ["calibrate", d / "garbage.cwa"], 2, "cannot decode"),
    ("unknown binary format", lambda d: ["calibrate", d / "data.xyz"], 2, "accepted"),
    ("binary file named .csv", lambda d: ["calibrate", d / "binary.csv"], 2, "not UTF-8"),
    ("empty file", lambda d: ["calibrate", d / "empty.csv"], 2, "empty"),
    ("no magic line", lambda d: ["calibrate", d / "nomagic.csv"], 2, "selfcal-recording"),
    ("apply without calibration", lambda d: ["apply", POSES, "--out", d / "o.csv"], 2, "--calibration"),
    ("apply with a malformed calibration", lambda d: ["apply", POSES, "--calibration", d / "bad_cal.json",
                                                      "--out", d / "o.csv"], 2, "bad_cal.json"),
    ("apply into a missing folder", lambda d: ["apply", POSES, "--calibration", d / "bad_cal.json",
                                               "--out", d / "no" / "o.csv"], 2, "does not exist"),
    ("unknown command", lambda d: ["calibrat", POSES], 2, "invalid choice"),
    ("negative days", lambda d: ["simulate", "--days", "-1", "--seed", "1", "--out", d / "s.csv"], 2, "--days"),
    ("diagnose an empty file", lambda d: ["diagnose", d / "empty.csv"], 2, "empty"),
    ("days not finite", lambda d: ["simulate", "--days", "inf", "--seed", "1", "--out", d / "s.csv"], 2, "--days"),
    ("days below a minute", lambda d: ["simulate", "--days", "1e-9", "--seed", "1", "--out", d / "s.csv"], 2, "--days"),
    ("negative seed", lambda d: ["simulate", "--days", "0.01", "--seed", "-1", "--out", d / "s.csv"], 2, "--seed"),
    ("simulate into a folder", lambda d: ["simulate", "--days", "0.01", "--seed", "1", "--out", d / "adir"], 2,
     "is a directory"),
    ("replay days beyond a century", lambda d: ["replay", "--days", "1e300", "--no-progress"], 2, "--days"),
    ("replay a negative seed", lambda d: ["replay", "--days", "1", "--seed", "-1", "--no-progress"], 2, "--seed"),
    ("config not UTF-8", lambda d: ["calibrate", POSES, "--config", d / "latin1.toml"], 2, "not UTF-8"),
    ("config is a folder", lambda d: ["calibrate", POSES, "--config", d / "adir"], 2, "cannot read"),
    ("a section given as a value", lambda d: ["calibrate", POSES, "--config", d / "section_value.toml"], 2,
     "[detector] must be a table"),
    ("calibration that is a JSON list", lambda d: ["apply", POSES, "--calibration", d / "list_cal.json",
                                                   "--out", d / "o.csv"], 2, "JSON object"),
    ("calibration that is a folder", lambda d: ["apply", POSES, "--calibration", d / "adir", "--out", d / "o.csv"],
     2, "cannot read"),
    ("calibrate over its input", lambda d: ["calibrate", d / "poses_copy.csv", "--out", d / "poses_copy.csv"], 2,
     "also an input"),
    ("history over its input", lambda d: ["calibrate", d / "poses_copy.csv", "--history", d / "poses_copy.csv"], 2,
     "also an input"),
    ("apply over its input", lambda d: ["apply", d / "poses_copy.csv", "--calibration", d / "list_cal.json",
                                        "--out", d / "poses_copy.csv"], 2, "also an input"),
    ("apply over its calibration", lambda d: ["apply", POSES, "--calibration", d / "list_cal.json",
                                              "--out", d / "list_cal.json"], 2, "also an input"),
    ("a summary over an input", lambda d: ["calibrate", d / "poses_copy.csv", POSES, "--summary",
                                           d / "poses_copy.csv"], 2, "also an input"),
    ("two recordings of one name", lambda d: ["calibrate", POSES, d / "adir" / ".." / "poses.csv", "--out-dir",
                                              d / "adir"], 2, "same name"),
    ("diagnose against a base with an effect", lambda d: ["diagnose", POSES, "--base-model",
                                                          "affine9+temperature_bias"], 2, "without effects"),
    ("serve a database in a missing folder", lambda d: ["serve", "--db", d / "no" / "x.db", "--port", "0"], 2,
     "does not exist"),  # (a traceback from the app's startup, exit 3)
    ("serve a folder as the database", lambda d: ["serve", "--db", f"sqlite:///{d / 'adir'}", "--port", "0"], 2,
     "is a folder"),
]


@pytest.mark.parametrize("name,argv,code,needle", CASES, ids=[c[0] for c in CASES])
def test_wrong_invocation(files, name, argv, code, needle):
    p = run_cli(*argv(files))
    assert p.returncode == code, (p.returncode, p.stderr)
    assert "Traceback" not in p.stderr, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.strip() and not ln.startswith("usage:") and not ln.startswith("  ")]
    assert len(lines) == 1, p.stderr
    assert needle.lower() in lines[0].lower(), lines[0]
    # a refused run wrote over nothing it reads
    assert (files / "poses_copy.csv").read_bytes() == POSES.read_bytes()
    assert (files / "list_cal.json").read_text() == "[1, 2]"


def test_unwritable_output_folder(files):
    if os.geteuid() == 0:
        pytest.skip("root writes anywhere")
    p = run_cli("calibrate", POSES, "--out", files / "readonly" / "cal.json")
    assert p.returncode == 2 and "not writable" in p.stderr


def test_version_and_closed_pipe():
    p = run_cli("--version")
    assert p.returncode == 0 and p.stdout.startswith("selfcal ")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = f"{sys.executable} -m selfcal.cli calibrate {POSES} --json | head -c 10"
    q = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, env=env, timeout=120)
    assert q.stdout == '{"format":'[:10] or len(q.stdout) == 10
    assert "Traceback" not in q.stderr and "BrokenPipe" not in q.stderr, q.stderr


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux-only")
def test_worker_idle_puts_the_refit_threads_under_sched_idle():
    """``selfcal worker --idle``: the process, and every thread it starts afterwards, run
    under SCHED_IDLE (checked in a child process: the policy cannot be undone unprivileged)."""
    code = ("import os, threading\n"
            "from selfcal.commands.worker import lower_priority\n"
            "assert os.sched_getscheduler(0) != os.SCHED_IDLE\n"
            "lower_priority(3, True)\n"
            "seen = []\n"
            "t = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0))); t.start(); t.join()\n"
            "print(os.sched_getscheduler(0) == os.SCHED_IDLE, seen == [os.SCHED_IDLE], os.nice(0))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["True", "True", str(3 + os.nice(0))]


def test_a_run_that_publishes_nothing_keeps_an_existing_history(tmp_path):
    """A failed calibrate (or replay --recording) emptied an existing --history file."""
    rec = tmp_path / "moving.csv"
    rng = np.random.default_rng(3)
    rows = "\n".join(f"{i / 20:.2f},{a:.4f},{b:.4f},{c:.4f}" for i, (a, b, c) in enumerate(rng.normal(0, 1, (400, 3))))
    rec.write_text("# selfcal-recording v1\n# kind=samples\nt_s,ax_g,ay_g,az_g\n" + rows + "\n")
    hist = tmp_path / "h.jsonl"
    hist.write_text('{"version": 1}\n')
    for argv in (["calibrate", rec, "--history", hist], ["replay", "--recording", rec, "--history", hist]):
        p = run_cli(*argv)
        assert p.returncode == 1 and "Traceback" not in p.stderr, p.stderr
        assert hist.read_text() == '{"version": 1}\n', argv


def test_an_interrupted_simulate_leaves_no_partial_file(tmp_path, monkeypatch):
    from selfcal.cli import main
    from selfcal.sim.simulator import Simulation

    real = Simulation.iter_samples

    def interrupted(self, *a, **k):
        it = real(self, *a, **k)
        yield next(it)
        raise KeyboardInterrupt

    monkeypatch.setattr(Simulation, "iter_samples", interrupted)
    out = tmp_path / "s.csv"
    assert main(["simulate", "--days", "0.2", "--seed", "1", "--out", str(out)]) != 0  # "interrupted"
    assert list(tmp_path.iterdir()) == []


def test_odd_line_ends_a_bom_and_a_late_bad_byte_are_named_exactly(tmp_path):
    from selfcal.io import iter_recording

    lines = ["# selfcal-recording v1", "# kind=samples", "t_s,ax_g,ay_g,az_g"] + [
        f"{i / 20:.2f},0.0,0.0,1.0" for i in range(8000)]
    cr = tmp_path / "cr.csv"
    cr.write_bytes("\r".join(lines).encode())
    p = run_cli("calibrate", cr)
    assert p.returncode == 2 and "lone CR" in p.stderr and len(p.stderr) < 400, p.stderr[:400]
    late = tmp_path / "late.csv"  # a bad byte past the first 64 KiB and 2 000 rows: its own line
    body = "\n".join(lines).encode().replace(b"\n349.00,0.0", b"\n349.00,\xff0.0")
    late.write_bytes(body + b"\n")
    with pytest.raises(InputError, match=r"late.csv:6984: not UTF-8"):
        for _ in iter_recording(late, block_rows=2000):
            pass
    bom = tmp_path / "bom.csv"  # a plain CSV (no header row) starting with a BOM
    bom.write_bytes(b"\xef\xbb\xbf" + "\n".join(ln for ln in lines[3:10]).encode() + b"\n")
    (rec,) = iter_recording(bom, columns=["t_s", "ax_g", "ay_g", "az_g"])
    assert len(rec) == 7 and rec.t_s[0] == 0.0  # the first row is data, not a header

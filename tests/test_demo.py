"""``selfcal demo``: the truth metric, the insole's sample source, and a scaled-down run
(2 insoles, 1 h of wear each, the service killed with SIGKILL halfway and restarted)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from selfcal.cli import main
from selfcal.config import load_config
from selfcal.demo import (
    SAMPLES_PER_PACKET,
    SimSource,
    demo_sim_config,
    make_simulation,
    norm_rms_mg,
    sphere_norm_rms_mg,
)
from selfcal.models import ErrorModel


def _sim(seed: int = 0, hours: float = 0.5):
    return make_simulation(demo_sim_config(load_config(None)), seed, hours)


def test_sphere_metric_is_zero_for_the_true_calibration_and_not_for_none():
    truth = _sim().truth.sensor
    model = ErrorModel("affine9")
    matrix, offset = model.linear(model.from_dict(truth.params()))  # canonical R, true offset
    assert sphere_norm_rms_mg(truth, matrix, offset) < 1e-6
    # the mounting rotation is invisible to norms: the full true matrix is as good
    assert sphere_norm_rms_mg(truth, truth.matrix, truth.offset) < 1e-6
    raw = sphere_norm_rms_mg(truth, np.eye(3), np.zeros(3))
    assert 5.0 < raw < 200.0
    # the same metric on a subset of directions (what the worn-pose figure uses)
    flat = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 0.995]])
    flat /= np.linalg.norm(flat, axis=1, keepdims=True)
    assert norm_rms_mg(truth, flat, matrix, offset) < 1e-6


class _Insole:
    subscribed = False


def test_sim_source_waits_for_a_subscriber_then_streams_whole_packets_from_shoe_on():
    sim = _sim(seed=3, hours=0.2)
    src = SimSource(sim, hours=0.2, piece=100)
    assert src.planned % SAMPLES_PER_PACKET == 0 and src.planned <= 0.2 * 3600 * 20
    on = np.flatnonzero(sim.schedule.on_foot)[0]
    assert src.t_start_s == pytest.approx(sim.schedule.start[on] / 20.0 - 300.0)
    # nobody listening: one placeholder sample per call, the simulation does not advance
    assert src()[1].shape == (1, 3) and src() is not None and src.emitted == 0
    src.insole = _Insole()
    assert src()[1].shape == (1, 3) and src.emitted == 0
    src.insole.subscribed = True
    chunks = []
    while (c := src()) is not None:
        chunks.append(c)
    t = np.concatenate([c[0] for c in chunks])
    assert len(t) == src.planned == src.emitted and src.done
    assert t[0] == pytest.approx(src.t_start_s, abs=0.05)
    assert np.allclose(np.diff(t), 0.05)  # uniformly sampled, no radio loss in the demo wearer
    assert all(c[1].shape[1] == 3 and c[2].shape[1] == 4 and len(c[3]) == len(c[0]) for c in chunks)
    # a link loss later would not hold samples back: no more placeholders once started
    src.insole.subscribed = False
    assert src() is None
    dirs = src.worn_directions()
    assert len(dirs) > 0 and np.allclose(np.linalg.norm(dirs, axis=1), 1.0)


@pytest.mark.service
@pytest.mark.ble
def test_demo_two_insoles_kill_and_restart_lose_nothing(tmp_path, monkeypatch, capsys):
    import selfcal.demo as demo_mod
    from selfcal.cli import main

    workdirs: list[Path] = []

    def mkdtemp(prefix: str = "") -> str:
        d = tmp_path / f"{prefix}{len(workdirs)}"
        d.mkdir()
        workdirs.append(d)
        return str(d)

    monkeypatch.setattr(demo_mod.tempfile, "mkdtemp", mkdtemp)
    t0 = time.monotonic()
    rc = main(["demo", "--devices", "2", "--hours", "1", "--kill-service-at", "0.5", "--json", "--no-progress"])
    wall = time.monotonic() - t0
    out = json.loads(capsys.readouterr().out)
    assert rc == 0
    print(f"demo wall time {wall:.1f} s")  # a figure, not a pass/fail: the machines are shared
    assert set(out) >= {"devices", "lost_samples", "service_restarts"}
    assert out["service_restarts"] == 1 and len(out["service_kills"]) == 1
    # events, not wall-clock fractions: the kill happened while samples were still streaming,
    # the service came back, and nothing acknowledged was lost (below)
    assert 0.0 < out["service_kills"][0]["at_fraction"] < 1.0
    assert out["lost_samples"] == 0
    assert [d["device_id"] for d in out["devices"]] == ["insole-01", "insole-02"]
    for d in out["devices"]:
        assert set(d) >= {"device_id", "samples_sent", "samples_stored", "status", "sphere_norm_rms_mg"}
        assert d["samples_sent"] == d["samples_stored"] > 0.99 * 3600 * 20
        assert d["status"] in ("uncalibrated", "provisional", "calibrated")
        if d["status"] != "uncalibrated":
            assert d["sphere_norm_rms_mg"] is not None and d["sphere_norm_rms_mg"] >= 0
            assert d["predicted_sphere_rms_mg"] is not None
        if d["status"] == "calibrated":  # a status is a promise
            assert d["promise_kept"], d
    gw = out["gateway"]
    assert gw["gaps"] == 0 and gw["rejected_batches"] == 0 and gw["malformed_packets"] == 0
    assert gw["samples_forwarded"] == sum(d["samples_sent"] for d in out["devices"])
    assert gw["retries"] > 0  # the outage was seen by the gateway and ridden out by its spool
    # the temporary folder (database, spool, service log) is gone
    assert workdirs and not any(d.exists() for d in workdirs)


@pytest.mark.slow
def test_demo_same_seed_same_figures(capsys):
    """Run twice with one seed, the demo reports the same figures (device clocks may start at
    other counts: the calibrator's blocks are counted from the first still window)."""
    figs = []
    for _ in range(2):
        assert main(["demo", "--devices", "1", "--hours", "1.5", "--seed", "11", "--json", "--no-progress"]) == 0
        out = json.loads(capsys.readouterr().out)
        figs.append([(d["status"], d["sphere_norm_rms_mg"], d["predicted_sphere_rms_mg"], d["worn_norm_rms_mg"],
                      d["versions"], d["samples_stored"]) for d in out["devices"]])
    assert figs[0] == figs[1]


def test_demo_help_names_the_default_hours():
    """`selfcal demo --help` states the default without importing the demo (kept in sync here)."""
    from selfcal.cli import build_parser
    from selfcal.demo import DEFAULT_HOURS

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    help_text = sub.choices["demo"].format_help()
    assert f"default {DEFAULT_HOURS:g}" in help_text


def _through_the_codec(src: SimSource) -> tuple[np.ndarray, ...]:
    """Every sample ``src`` streams, as the gateway receives it: packets of
    ``SAMPLES_PER_PACKET`` encoded as the virtual insole encodes them (the packet's mean
    temperature), decoded, on device time ``seq / rate``: (t_s, acc_g, temp_c, pressure_kpa)."""
    from selfcal.gateway import codec

    src.started = True
    parts = []
    while (chunk := src()) is not None:
        parts.append(chunk)
    _, acc, prs, temp = (np.concatenate([p[i] for p in parts]) for i in range(4))
    n = len(acc) - len(acc) % SAMPLES_PER_PACKET
    out_acc, out_prs, out_temp = [], [], []
    for lo in range(0, n, SAMPLES_PER_PACKET):
        sl = slice(lo, lo + SAMPLES_PER_PACKET)
        packet = codec.decode_packet(codec.encode_packet(lo, acc[sl], prs[sl], float(np.mean(temp[sl]))))
        out_acc.append(packet.acc_g)
        out_prs.append(packet.pressure_kpa)
        out_temp.append(np.full(packet.n, packet.temp_c))
    return (np.arange(n) / src.rate_hz, np.concatenate(out_acc), np.concatenate(out_temp), np.concatenate(out_prs))


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(8))
def test_the_demos_wear_through_the_codec_keeps_the_sphere_promise_of_every_version(seed):
    """The demo's wear (``DEFAULT_HOURS`` from shoe-on) as the service gets it, through the
    BLE codec and in the gateway's batches: every published version, provisional as well as
    calibrated, keeps its sphere promise (true whole-sphere error <= 2.5 x predicted +
    0.05 mg, :mod:`selfcal.scoring`). Seeds 0-7. While the simulator quantised in 3.91-mg
    steps, which the codec's 1/4096 g units do not hold, seed 1 broke it (the demo's
    insole-02: 16.1 mg against 6.2 predicted)."""
    from selfcal.calibrator import OnlineCalibrator
    from selfcal.demo import BATCH_SAMPLES, DEFAULT_HOURS
    from selfcal.scoring import PROMISE_RATIO, PROMISE_SLACK_MG, TruthScorer

    cfg = load_config(None)
    sim = make_simulation(demo_sim_config(cfg), seed, DEFAULT_HOURS)
    t, acc, temp, prs = _through_the_codec(SimSource(sim, DEFAULT_HOURS))
    cal = OnlineCalibrator(config={k: v for k, v in cfg.items() if k not in ("service", "gateway")})
    versions = []
    for lo in range(0, len(t), BATCH_SAMPLES):
        sl = slice(lo, lo + BATCH_SAMPLES)
        versions += [dict(ev["calibration"], version=len(versions) + 1)
                     for ev in cal.feed_samples(t[sl], acc[sl], temp_c=temp[sl], pressure_kpa=prs[sl])
                     if ev.get("published")]
    assert len(versions) >= 3
    scorer = TruthScorer(sim.truth.to_dict(), versions[-1]["model"])
    for v in versions:
        s = scorer.score(v)
        assert s["true_mg"] <= PROMISE_RATIO * s["predicted_mg"] + PROMISE_SLACK_MG, (v["version"], v["status"], s)


def test_a_stall_anywhere_in_the_demo_ends_at_its_deadline_with_a_clear_error():
    """The deadline was checked only in the streaming loop: a run stalled before it (an
    insole that never connected) ignored --timeout for 24 minutes."""
    import asyncio

    from selfcal.demo import within
    from selfcal.errors import SelfcalError

    async def stalled():
        await asyncio.Event().wait()

    with pytest.raises(SelfcalError, match="did not finish within"):  # (the coroutine never ends by itself)
        asyncio.run(within(stalled(), 0.2, "the demo did not finish within 0 s"))


def test_sigterm_ends_the_demo_as_ctrl_c_does():
    import os
    import signal

    from selfcal.demo import _terminate_as_interrupt

    old = _terminate_as_interrupt()
    try:
        with pytest.raises(KeyboardInterrupt):  # (the demo's finally: service stopped, folder removed)
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
    finally:
        signal.signal(signal.SIGTERM, old)


def test_bumbles_own_callback_errors_are_hidden_and_no_other_is():
    import logging

    from selfcal.demo import _BumbleCallbackErrors

    def record_of(filename: str) -> logging.LogRecord:
        try:
            exec(compile("raise RuntimeError('invalid state')", filename, "exec"))
        except RuntimeError as exc:
            info = (type(exc), exc, exc.__traceback__)
        return logging.LogRecord("asyncio", logging.ERROR, "x", 1, "Exception in callback", None, info)

    f = _BumbleCallbackErrors()
    assert not f.filter(record_of("/venv/site-packages/bumble/host.py"))
    assert f.filter(record_of("/work/selfcal/gateway/gateway.py"))
    assert f.filter(logging.LogRecord("asyncio", logging.ERROR, "x", 1, "no exception", None, None))

"""Scale-out on PostgreSQL: 3 API processes and 2 refit workers; one of each killed mid-ingest.

Runs in the ``SELFCAL_TEST_BACKEND=postgresql`` pass (``scripts/test.sh`` runs it). The
real OnlineCalibrator; 4 insoles, each a stream of still poses 10 minutes apart (so a
few versions are published per device). Senders post each device's batches in seq
order and retry a batch whose connection broke (a killed API process) until it is
acknowledged. Mid-ingest one ``selfcal worker`` and one API process get ``kill -9``.

Afterwards, for every device: every acknowledged batch is stored once and fed once
(``samples_processed`` counts each fed sample once; every batch row is ``fed``), and
the published versions equal those of a single in-process calibrator fed the same
stream (the same number, the same parameters bit for bit).
"""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from service_helpers import KEYS, ServerProcess, WorkerProcess, child_pids, only_postgres

pytestmark = [pytest.mark.service, only_postgres]

RATE_HZ = 20.0
DEVICES = [f"insole-{i:02d}" for i in range(4)]
N_POSES = 60


def device_stream(seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Batches (t_s, acc_g): each a 4-s still pose then 1.5 s of motion; poses 10 min apart."""
    rng = np.random.default_rng(seed)
    matrix = np.diag(1.0 + rng.uniform(-0.03, 0.03, 3))
    offset = rng.uniform(-0.06, 0.06, 3)
    d = rng.normal(size=(N_POSES, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    out, t0 = [], 0.0
    for direction in d:
        a = np.vstack([np.tile(direction, (80, 1)), direction + rng.normal(0, 0.4, (30, 3))])
        t = t0 + np.arange(len(a)) / RATE_HZ
        out.append((t, offset + a @ np.linalg.inv(matrix).T + rng.normal(0, 2e-3, a.shape)))
        t0 = t[-1] + 600.0
    return out


def reference_versions(config_path, batches) -> list[dict]:
    """What one in-process calibrator publishes on the same stream (batch by batch)."""
    from selfcal.calibrator import OnlineCalibrator
    from selfcal.config import load_config

    cfg = {k: v for k, v in load_config(str(config_path)).items() if k not in ("service", "gateway")}
    cal = OnlineCalibrator(config=cfg, model="affine9")
    out = []
    for t, a in batches:
        for ev in cal.feed_samples(t, a, temp_c=np.full(len(t), 25.0)) or []:
            if ev.get("published"):
                out.append(ev["calibration"]["params"] if ev.get("calibration") else cal.calibration()["params"])
    return out


def post_until_acked(url: str, device: str, seq: int, t: np.ndarray, a: np.ndarray, stop: threading.Event) -> None:
    body = {"seq": seq, "t_s": t.tolist(), "ax_g": a[:, 0].tolist(), "ay_g": a[:, 1].tolist(),
            "az_g": a[:, 2].tolist(), "temp_c": [25.0] * len(t)}
    while not stop.is_set():
        try:
            r = httpx.post(f"{url}/devices/{device}/samples", json=body, timeout=10,
                           headers={"Authorization": f"Bearer {KEYS['ingest']}"})
            if r.status_code == 200:
                return
            assert r.status_code == 503, r.text  # only "retry later" is acceptable
        except httpx.HTTPError:
            pass  # the API process behind this connection was killed: resend
        time.sleep(0.1)


def test_kill9_of_a_worker_and_an_api_process_loses_nothing_and_matches_one_process(tmp_path):
    streams = {dev: device_stream(100 + i) for i, dev in enumerate(DEVICES)}
    srv = ServerProcess(tmp_path / "scale.db", tmp_path, calibrator=None,  # the real OnlineCalibrator
                        args=["--workers", "3", "--no-refit"], env={"SELFCAL_LEASE_TTL_S": "3"})
    workers = [WorkerProcess(srv, "a"), WorkerProcess(srv, "b")]
    stop = threading.Event()
    try:
        srv.start(timeout_s=60)
        for w in workers:
            w.start()
        deadline = time.monotonic() + 60
        while not all(w.log.exists() and "selfcal worker" in w.log.read_text() for w in workers):
            assert time.monotonic() < deadline, "the workers did not start"
            time.sleep(0.1)
        # each worker at its default: 4 refit threads, cycles of several devices in flight at once
        assert all("threads=4," in w.log.read_text() for w in workers), [w.log.read_text() for w in workers]
        sent = {dev: 0 for dev in DEVICES}

        def sender(dev: str) -> None:
            for seq, (t, a) in enumerate(streams[dev]):
                post_until_acked(srv.url, dev, seq, t, a, stop)
                sent[dev] = seq + 1
                time.sleep(0.03)

        threads = [threading.Thread(target=sender, args=(d,)) for d in DEVICES]
        for th in threads:
            th.start()
        while sum(sent.values()) < 0.35 * len(DEVICES) * N_POSES:
            time.sleep(0.05)
        # uvicorn's spawned API processes (multiprocessing's resource tracker is a child too)
        api_children = [c for c in child_pids(srv.proc.pid, "spawn_main")
                        if "resource_tracker" not in Path(f"/proc/{c}/cmdline").read_text(errors="replace")]
        assert len(api_children) == 3, api_children
        import psycopg

        mark = f":{workers[0].proc.pid}:"
        deadline = time.monotonic() + 30
        with psycopg.connect(srv.db_arg, autocommit=True) as conn:  # kill it while it holds leases
            while True:
                owners = [r[0] for r in conn.execute(
                    "SELECT lease_owner FROM devices WHERE lease_owner IS NOT NULL").fetchall()]
                if any(mark in o for o in owners) or time.monotonic() > deadline:
                    break
                time.sleep(0.005)
        assert any(mark in o for o in owners), f"worker a never held a lease: {owners}"
        workers[0].kill9()                          # a refit worker, mid-ingest, holding leases
        os.kill(api_children[0], signal.SIGKILL)    # an API process, mid-ingest
        for th in threads:
            th.join(timeout=240)
        assert all(n == N_POSES for n in sent.values()), sent
        # uvicorn's supervisor replaces the killed API process (it looks every half second)
        deadline = time.monotonic() + 30
        while True:
            now_children = [c for c in child_pids(srv.proc.pid, "spawn_main")
                            if "resource_tracker" not in Path(f"/proc/{c}/cmdline").read_text(errors="replace")]
            if len(now_children) == 3 or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        assert api_children[0] not in now_children and len(now_children) == 3, (api_children, now_children)
        # the surviving worker takes the killed one's devices over once its leases expire
        deadline = time.monotonic() + 120
        with srv.client("read") as c:
            while time.monotonic() < deadline:
                bodies = {d: c.get(f"/devices/{d}/calibration").json() for d in DEVICES}
                if all(b["processed_seq"] == N_POSES - 1 for b in bodies.values()):
                    break
                time.sleep(0.2)
            histories = {d: c.get(f"/devices/{d}/calibration/history").json() for d in DEVICES}
        for dev in DEVICES:
            b = bodies[dev]
            n_samples = sum(len(t) for t, _ in streams[dev])
            assert b["processed_seq"] == N_POSES - 1, (dev, b)
            assert b["batches_stored"] == N_POSES, (dev, b)            # stored once
            assert b["samples_processed"] == n_samples, (dev, b)       # fed once (a refeed would add)
            assert b["rejected_samples"] == 0, (dev, b)
            got = [v["calibration"]["params"] for v in histories[dev]["versions"] if v["source"] == "refit"]
            want = reference_versions(srv.config, streams[dev])
            assert len(got) == len(want) >= 3, (dev, len(got), len(want))
            # bit for bit, however the workers' cycles grouped the batches (the pose store
            # adds a cell's windows in order: before, the last bits moved with the timing)
            for g, w in zip(got, want):
                for k in w:
                    assert g[k] == w[k], (dev, k, g[k], w[k])
        with psycopg.connect(srv.db_arg) as conn:
            states = dict(conn.execute("SELECT state, COUNT(*) FROM batches GROUP BY state").fetchall())
        assert states == {1: len(DEVICES) * N_POSES}, states  # every batch fed, none pending or rejected
        assert workers[1].proc.poll() is None
    finally:
        stop.set()
        for w in workers:
            w.stop()
        srv.stop()


def test_metrics_add_up_over_api_processes(tmp_path):
    """A scrape reaches one API process; its /metrics counts the batches every process stored."""
    from service_helpers import batch_json

    shared = tmp_path / "metrics"
    srv = ServerProcess(tmp_path / "m.db", tmp_path, calibrator="service_fakes:FakeCalibrator",
                        args=["--workers", "3"], env={"SELFCAL_METRICS_DIR": str(shared)})
    try:
        srv.start(timeout_s=60)
        for seq in range(60):  # a new connection each: the kernel spreads them over the processes
            r = httpx.post(f"{srv.url}/devices/m-dev/samples", json=batch_json(seq), timeout=10,
                           headers={"Authorization": f"Bearer {KEYS['ingest']}"})
            assert r.status_code == 200, r.text
        time.sleep(1.5)  # each process publishes its counters about once a second
        counted = []
        for f in shared.glob("*.json"):
            rows = json.loads(f.read_text())["counters"]
            counted += [v for name, _, v in rows if name == "selfcal_ingest_batches_total" and v > 0]
        assert len(counted) >= 2 and sum(counted) == 60, counted  # several processes stored batches
        for _ in range(5):  # whichever process answers, the sum is the same
            text = httpx.get(f"{srv.url}/metrics", headers={"Authorization": f"Bearer {KEYS['read']}"},
                             timeout=10).text
            assert "selfcal_ingest_batches_total 60\n" in text, [ln for ln in text.splitlines() if "batches_total" in ln]
            writes = float(re.search(r"^selfcal_db_writes_total (\S+)$", text, re.M).group(1))
            assert writes >= 60  # every process's committed writes, not only the answering one's
    finally:
        srv.stop()

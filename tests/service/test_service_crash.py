"""``kill -9`` at random moments during ingest and refits: nothing acknowledged is lost,
nothing is counted twice, and the calibrator resumes exactly (fake calibrator checksums)."""

from __future__ import annotations

import threading
import time

import httpx
import numpy as np
import pytest

from service_helpers import ServerProcess, auth, batch_json, t_ms_sum

pytestmark = pytest.mark.service

N_BATCHES = 300
N_SAMPLES = 20
DEVICES = ["crash-a", "crash-b", "crash-c"]


class Gateway(threading.Thread):
    """Sends seq 0..N-1 for one device, retrying each batch until it is acknowledged."""

    def __init__(self, srv: ServerProcess, device_id: str, bodies: list[dict]):
        super().__init__(daemon=True)
        self.srv, self.device_id, self.bodies = srv, device_id, bodies
        self.acked: list[tuple[int, float]] = []  # (seq, monotonic time of the ack)
        self.retries = 0
        self.error: str | None = None

    def run(self) -> None:
        deadline = time.monotonic() + 120
        with httpx.Client(headers=auth("ingest"), timeout=5.0) as client:
            self._run(client, deadline)

    def _run(self, client: httpx.Client, deadline: float) -> None:
        for body in self.bodies:
            while True:
                if time.monotonic() > deadline:
                    self.error = "gave up"
                    return
                try:
                    r = client.post(f"{self.srv.url}/devices/{self.device_id}/samples", json=body)
                except httpx.TransportError:
                    self.retries += 1
                    time.sleep(0.02)
                    continue
                if r.status_code != 200:
                    self.error = f"seq {body['seq']}: {r.status_code} {r.text}"
                    return
                self.acked.append((body["seq"], time.monotonic()))
                break


def test_kill9_mid_ingest_loses_nothing_acknowledged_and_counts_nothing_twice(tmp_path):
    rng = np.random.default_rng(1234)
    srv = ServerProcess(tmp_path / "crash.db", tmp_path, calibrator="service_fakes:FakeCalibrator")
    bodies = {d: [batch_json(s, n=N_SAMPLES, rng=np.random.default_rng(1000 * k + s)) for s in range(N_BATCHES)]
              for k, d in enumerate(DEVICES)}
    srv.start()
    gateways = [Gateway(srv, d, bodies[d]) for d in DEVICES]
    for g in gateways:
        g.start()
    kills = 0
    total = N_BATCHES * len(DEVICES)
    try:
        # three kills at random moments of the ingest, as fractions of the batches acknowledged
        # (a fixed 0.3-0.9 s sleep found the ingest already over on a fast machine: no kill)
        for frac in np.sort(rng.uniform(0.1, 0.9, 3)):
            deadline = time.monotonic() + 120
            while sum(len(g.acked) for g in gateways) < frac * total and any(g.is_alive() for g in gateways):
                assert time.monotonic() < deadline, "the ingest stalled"
                time.sleep(0.002)
            if not any(g.is_alive() for g in gateways):
                break
            kill_time = time.monotonic()
            srv.kill9()
            kills += 1
            # what was acknowledged before the kill must be there after the restart
            before = {d: [s for s, t in g.acked if t < kill_time] for d, g in zip(DEVICES, gateways)}
            srv.start()
            with srv.client("ingest") as c:
                for d in DEVICES:
                    for s in before[d][-15:]:
                        r = c.post(f"/devices/{d}/samples", json=bodies[d][s])
                        assert r.status_code == 200 and r.json()["duplicate"] is True, (d, s, r.text)
        for g in gateways:
            g.join(timeout=150)
            assert g.error is None, g.error
            assert [s for s, _ in g.acked] == list(range(N_BATCHES))
        assert kills >= 1
        for d in DEVICES:
            cal = srv.wait_processed(d, N_BATCHES - 1)
            assert cal["batches_stored"] == N_BATCHES
            assert cal["samples_processed"] == N_BATCHES * N_SAMPLES
            # the calibrator's own count and checksum: every sample fed exactly once
            assert cal["last_refit"]["n_samples"] == N_BATCHES * N_SAMPLES
            assert cal["last_refit"]["t_ms_sum"] == sum(t_ms_sum(b) for b in bodies[d])
            with srv.client("read") as c:
                hist = c.get(f"/devices/{d}/calibration/history").json()
            assert [v["status"] for v in hist["versions"]] == ["provisional", "calibrated"]  # published once each
        # one more kill with the worker idle, then a restart: state is exactly the same
        states = {}
        with srv.client("read") as c:
            for d in DEVICES:
                states[d] = c.get(f"/devices/{d}/calibration").json()
        srv.kill9()
        srv.start()
        with srv.client("read") as c:
            for d in DEVICES:
                assert c.get(f"/devices/{d}/calibration").json() == states[d]
    finally:
        srv.kill9()

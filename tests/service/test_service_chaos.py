"""Chaos suite (bounded in time, loopback only): a real ``selfcal serve`` with the fake
calibrator (it checksums every sample it is fed) is killed with SIGKILL at random
moments while three devices send with 4 batches in flight, out of order, with
resends, bit-flipped binary batches and implausible admin writes; the database is made
read-only (``chattr +i``) and the disk full (a small tmpfs) on the way, when running as
root. Afterwards, for every device: samples acknowledged = samples stored = samples fed
+ samples rejected with a reason, the calibrator was fed each sample once, and nothing
was published from a refused request."""

from __future__ import annotations

import concurrent.futures as cf
import random
import time

import httpx
import numpy as np
import pytest

from service_faults import can_chattr, can_mount, chattr, database_files, fill_disk, flip_bit, mount_tmpfs, unmount
from service_helpers import backend, ServerProcess, batch_json, t_ms_sum

from selfcal_service.schemas import BINARY_MEDIA_TYPE, SampleBatchIn

DEVICES = ("chaos-a", "chaos-b", "chaos-c")
N_BATCHES = 90  # per device, 20 samples each
KILLS = 5


class Sender:
    """A gateway-like client: every batch is resent until it is acknowledged."""

    def __init__(self, srv: ServerProcess):
        self.srv = srv
        self.bodies = {(d, s): batch_json(s, rng=np.random.default_rng([hash(d) % 1000, s]))
                       for d in DEVICES for s in range(N_BATCHES)}
        self.acked: set[tuple[str, int]] = set()
        self.codes: list[int] = []

    def post(self, key: tuple[str, int], binary: bool) -> None:
        dev, seq = key
        body = self.bodies[key]
        try:
            with self.srv.client("ingest") as c:
                if binary:
                    raw = SampleBatchIn.model_validate(body).to_batch().to_bytes(crc=True)
                    r = c.post(f"/devices/{dev}/samples", content=raw,
                               headers={"Content-Type": BINARY_MEDIA_TYPE})
                else:
                    r = c.post(f"/devices/{dev}/samples", json=body)
        except httpx.HTTPError:
            return  # server down: resent later
        self.codes.append(r.status_code)
        if r.status_code == 200:
            self.acked.add(key)

    def send_round(self, keys: list[tuple[str, int]], rng: random.Random) -> None:
        with cf.ThreadPoolExecutor(4 * len(DEVICES)) as pool:  # 4 in flight per device
            list(pool.map(lambda k: self.post(k, rng.random() < 0.5), keys))


@pytest.mark.slow
def test_chaos_every_acknowledged_sample_is_fed_once_or_rejected_with_a_reason(tmp_path):
    sqlite = backend() == "sqlite"  # file faults (read-only, disk full) are SQLite's; kills and flips are not
    read_only_possible = sqlite and can_chattr()
    rng = random.Random(2026)
    mnt = None
    if sqlite and can_mount():
        mnt = tmp_path / "mnt"
        mnt.mkdir()
        assert mount_tmpfs(mnt, "8m")
    db = (mnt or tmp_path) / "selfcal.db"
    srv = ServerProcess(db, tmp_path, calibrator="service_fakes:FakeCalibrator",
                        env={"SELFCAL_REORDER_WINDOW_S": "0.5"})
    sender = Sender(srv)
    faults: list[str] = []
    history_before_bad_puts: dict[str, list] = {}
    try:
        srv.start()
        # the order of sending: windows of 8 shuffled (out of order), some resent twice
        order = []
        for lo in range(0, N_BATCHES, 8):
            chunk = [(d, s) for s in range(lo, min(N_BATCHES, lo + 8)) for d in DEVICES]
            rng.shuffle(chunk)
            order += chunk + rng.sample(chunk, 3)
        kill_at = sorted(rng.sample(range(1, len(order) // 24), KILLS))
        rounds = [order[i:i + 24] for i in range(0, len(order), 24)]
        for i, keys in enumerate(rounds):
            if i == 3 and read_only_possible:  # read-only database for one round
                chattr(database_files(db), "+i")
                sender.send_round(keys, rng)
                chattr(database_files(db), "-i")
                faults.append("read-only")
            elif i == 5 and mnt is not None:  # full disk for one round
                filler = fill_disk(mnt)
                sender.send_round(keys, rng)
                filler.unlink()
                faults.append("disk-full")
            else:
                sender.send_round(keys, rng)
            if i == 2:  # bit-flipped binary batches and implausible admin writes: all refused
                with srv.client() as c:
                    for dev in DEVICES:
                        history_before_bad_puts[dev] = c.get(f"/devices/{dev}/calibration/history").json()["versions"]
                        raw = SampleBatchIn.model_validate(sender.bodies[(dev, 50)]).to_batch().to_bytes(crc=True)
                        for _ in range(5):
                            r = c.post(f"/devices/{dev}/samples", content=flip_bit(raw, rng),
                                       headers={"Content-Type": BINARY_MEDIA_TYPE})
                            assert r.status_code == 422, r.text
                        bad = c.put(f"/devices/{dev}/calibration",
                                    json={"matrix": [[0, 0, 0], [0, 0, 0], [0, 0, 0]], "offset": [0, 0, 0]})
                        assert bad.status_code == 422
            if kill_at and i == kill_at[0]:
                kill_at.pop(0)
                time.sleep(rng.uniform(0.0, 0.3))
                srv.kill9()
                faults.append("kill -9")
                srv.start()
        # resend everything not acknowledged (a gateway's spool), until all are
        for _ in range(20):
            missing = [k for k in sender.bodies if k not in sender.acked]
            if not missing:
                break
            sender.send_round(missing, rng)
            time.sleep(0.2)
        assert not [k for k in sender.bodies if k not in sender.acked]
        assert 500 not in sender.codes
        assert faults.count("kill -9") == KILLS
        # settle, then account for every device
        bodies = [srv.wait_settled(d, N_BATCHES, timeout_s=60) for d in DEVICES]
        with srv.client("read") as c:
            for dev, body in zip(DEVICES, bodies):
                acked = 20 * sum(1 for k in sender.acked if k[0] == dev)
                assert acked == N_BATCHES * 20
                assert body["batches_stored"] * 20 == acked, body  # stored once each
                assert body["samples_processed"] + body["rejected_samples"] == acked, body
                if body["rejected_batches"]:
                    assert body["last_rejection"]["reason"].split(":")[0] in ("late", "calibrator")
                fed = body["last_refit"]
                assert fed["n_samples"] == body["samples_processed"]  # each sample fed once
                history = c.get(f"/devices/{dev}/calibration/history").json()["versions"]
                assert all(v["source"] != "factory" for v in history)  # no refused PUT published
                assert history[: len(history_before_bad_puts[dev])] == history_before_bad_puts[dev]
            if not any(b["rejected_batches"] for b in bodies):  # then the checksum is exact
                for dev, body in zip(DEVICES, bodies):
                    want = sum(t_ms_sum(sender.bodies[(dev, s)]) for s in range(N_BATCHES))
                    assert body["last_refit"]["t_ms_sum"] == want
        print(f"\nchaos: faults {faults}; rejected per device "
              f"{[b['rejected_batches'] for b in bodies]}; HTTP codes "
              f"{ {code: sender.codes.count(code) for code in sorted(set(sender.codes))} }")
    finally:
        srv.kill9()
        if mnt is not None:
            unmount(mnt)

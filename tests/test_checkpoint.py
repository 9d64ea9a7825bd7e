"""Delta checkpoints (selfcal/checkpoint.py): a base state and a patch against it give the
full state back byte for byte, whatever happened to the pose store in between (new
cells, windows added to old ones, cells coarsened and dropped past the bound)."""

import json

import numpy as np
import pytest

from selfcal.calibrator import OnlineCalibrator
from selfcal.checkpoint import apply_patch, make_patch, row_digests
from selfcal.errors import InputError


def _poses(seed: int, k: int, n_dirs: int = 60):
    """``k`` still poses over ``n_dirs`` directions, 10 min apart, 20-25 degC."""
    rng = np.random.default_rng(seed)
    dirs = rng.standard_normal((n_dirs, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    mean = dirs[rng.integers(0, n_dirs, k)] * (1 + 1e-3 * rng.standard_normal((k, 1)))
    return mean, np.full((k, 3), 2e-3), np.full(k, 40.0), 600.0 * np.arange(k), 20.0 + 5 * rng.random(k)


def _calibrator(max_cells: int | None = None) -> OnlineCalibrator:
    from selfcal.config import load_config

    cfg = load_config(None)
    if max_cells is not None:
        cfg["poses"] = dict(cfg.get("poses", {}), max_cells=max_cells)
    return OnlineCalibrator(cfg, "affine9")


def _fed_past_a_base(seed: int):
    """A calibrator fed 60 of 120 poses, its state then (the base text and what a writer
    keeps of it), and the calibrator fed the other 60."""
    poses = _poses(seed, 120)
    cal = _calibrator()
    cal.feed_poses(*[a[:60] for a in poses])
    base_text = cal.to_json()
    base = cal.checkpoint_base(base_text)
    cal.feed_poses(*[a[60:] for a in poses])
    return cal, base_text, base


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("max_cells", [None, 16])
def test_a_patch_applied_to_its_base_gives_the_full_state_byte_for_byte(seed, max_cells):
    poses = _poses(seed, 400)
    cal = _calibrator(max_cells)
    cal.feed_poses(*[a[:50] for a in poses])
    base_text = cal.to_json()
    base = cal.checkpoint_base(base_text)
    checked = 0
    for i in range(50, 400, 35):
        cal.feed_poses(*[a[i:i + 35] for a in poses])
        full = cal.to_json()
        patch = cal.checkpoint_patch(base)
        state, again = apply_patch(base_text, patch)
        assert json.dumps(state, allow_nan=True, separators=(",", ":")) == full
        assert np.array_equal(again.digests, base.digests) and again.crc32 == base.crc32
        restored, _ = OnlineCalibrator.from_checkpoint(base_text, patch)
        assert restored.to_json() == full
        checked += 1
    assert checked == 10
    if max_cells is not None:  # the bound merged cells, so rows left the base and others moved
        assert cal.store.n_merged > 0 and len(cal.store) <= max_cells


def test_a_worn_states_patch_holds_the_changed_cells_only():
    """After more windows in a few known cells, the patch carries those rows and not the others."""
    poses = _poses(3, 600, n_dirs=200)
    cal = _calibrator()
    cal.feed_poses(*poses)
    base_text = cal.to_json()
    base = cal.checkpoint_base(base_text)
    m = len(cal.store)
    again = tuple(a[-3:] for a in poses[:3]) + (poses[3][-3:] + 600.0 * 3, poses[4][-3:])  # 3 more windows
    cal.feed_poses(*again)
    patch = cal.checkpoint_patch(base)
    store_patch = json.loads(patch)["state"]["store"]
    assert 1 <= len(store_patch["key"]) <= 3 < m
    assert len(patch) < len(base_text) / 3
    assert OnlineCalibrator.from_checkpoint(base_text, patch)[0].to_json() == cal.to_json()


def test_a_patch_refuses_another_base_and_bad_text():
    cal, base_text, base = _fed_past_a_base(4)
    patch = cal.checkpoint_patch(base)
    other = base_text.replace('"n_refits":', '"n_refits": ', 1)  # same content, other bytes
    with pytest.raises(InputError, match="another base"):
        apply_patch(other, patch)
    with pytest.raises(InputError, match="not JSON"):
        apply_patch(base_text, patch[:-5])
    with pytest.raises(InputError, match="format"):
        apply_patch(base_text, json.dumps({"format": "selfcal-calibrator-state"}))
    broken = json.loads(patch)
    broken["state"]["store"]["key"] = broken["state"]["store"]["key"] + [12345]
    with pytest.raises(InputError, match="row order"):
        apply_patch(base_text, json.dumps(broken))


def test_row_digests_see_every_bit_of_a_row():
    rng = np.random.default_rng(7)
    m = 50
    key = rng.integers(0, 2**40, m)
    stats = rng.standard_normal((m, 20))
    stats[3, 4] = 0.0
    t_first, t_last = rng.random(m) * 1e5, rng.random(m) * 1e5
    d = row_digests(key, stats, t_first, t_last)
    assert len(np.unique(d)) == m
    assert np.array_equal(d, row_digests(key.copy(), stats.copy(), t_first.copy(), t_last.copy()))
    for edit in range(23):  # one element of row 3 changed by one bit (or 0.0 -> -0.0)
        k, s, f, last = key.copy(), stats.copy(), t_first.copy(), t_last.copy()
        if edit == 0:
            k[3] ^= 1
        elif edit <= 20:
            s[3, edit - 1] = -0.0 if s[3, edit - 1] == 0 else np.nextafter(s[3, edit - 1], np.inf)
        elif edit == 21:
            f[3] = np.nextafter(f[3], 0)
        else:
            last[3] = np.nextafter(last[3], 0)
        e = row_digests(k, s, f, last)
        assert e[3] != d[3] and np.array_equal(np.delete(e, 3), np.delete(d, 3)), edit


def test_make_patch_against_an_empty_base():
    """A base with no cell: every row is new."""
    cal = _calibrator()
    base_text = cal.to_json()
    base = cal.checkpoint_base(base_text)
    assert len(base.digests) == 0
    poses = _poses(5, 30)
    cal.feed_poses(*poses)
    patch = make_patch(cal.state(store_rows=False), cal.store, base)
    assert OnlineCalibrator.from_checkpoint(base_text, patch)[0].to_json() == cal.to_json()


def test_the_row_order_round_trips_and_a_corrupt_one_is_refused():
    from selfcal.checkpoint import _decode_order, _encode_order

    rng = np.random.default_rng(8)
    for order in (np.arange(5000), np.r_[np.arange(3000), -1, -1, np.arange(3001, 4000)], np.array([], int),
                  rng.permutation(800), np.where(rng.random(900) < 0.1, -1, np.arange(900))):
        assert np.array_equal(_decode_order(_encode_order(order)), order)
    assert len(_encode_order(np.arange(5000))) < 200  # runs of +1 cost next to nothing
    cal, base_text, base = _fed_past_a_base(6)
    broken = json.loads(cal.checkpoint_patch(base))
    broken["state"]["store"]["from_base"] = _encode_order(np.full(len(cal.store), -7))
    with pytest.raises(InputError, match="row order"):
        apply_patch(base_text, json.dumps(broken))
    broken["state"]["store"]["from_base"] = "not base64 zlib"
    with pytest.raises(InputError):
        apply_patch(base_text, json.dumps(broken))


@pytest.mark.parametrize("seed", [0, 1])
def test_fields_equal_to_the_bases_are_named_not_repeated(seed):
    """Format 2: a field whose JSON is the base's (the configuration, always) is named in
    ``same`` and holds null; a field that changed is written. Applied, the state is the
    full one byte for byte; a format-1 patch (every field written) still applies; a
    patch naming a field the base lacks is refused."""
    cal, base_text, base = _fed_past_a_base(seed)
    assert {"config", "detector"} <= set(base.fields)
    full = cal.to_json()
    patch = json.loads(cal.checkpoint_patch(base))
    assert patch["format_version"] == 2 and "config" in patch["same"]
    was, now = json.loads(base_text), json.loads(full)
    unchanged = {k for k in base.fields if json.dumps(was[k]) == json.dumps(now[k])}
    assert set(patch["same"]) == unchanged and unchanged != set(base.fields)  # something changed
    assert all(patch["state"][k] is None for k in patch["same"])
    assert all(patch["state"][k] == now[k] for k in set(base.fields) - unchanged)
    state, again = apply_patch(base_text, json.dumps(patch))
    assert json.dumps(state, allow_nan=True, separators=(",", ":")) == full
    assert again.fields == base.fields

    v1 = dict(patch, format_version=1, state=dict(patch["state"], **{k: json.loads(full)[k] for k in patch["same"]}))
    del v1["same"]
    assert json.dumps(apply_patch(base_text, json.dumps(v1))[0], allow_nan=True, separators=(",", ":")) == full

    # a patch naming a field the base or its state lacks, the store, or not as a list: refused
    for bad in (dict(patch, same=patch["same"] + ["no_such_field"]), dict(patch, same="config"),
                dict(patch, same=["store"]), dict(patch, same=[["config"]]), dict(patch, same=[3]),
                dict(patch, format_version=True),
                dict(patch, state=dict(patch["state"], store=dict(patch["state"]["store"], key=[2**70])))):
        with pytest.raises(InputError):
            apply_patch(base_text, json.dumps(bad))

    # against a base of the state itself, every field is named
    again_patch = json.loads(cal.checkpoint_patch(cal.checkpoint_base(full)))
    assert set(again_patch["same"]) == set(cal.checkpoint_base(full).fields) >= {"config"}

"""Pose store: the gate and the sums do not depend on how windows are split into calls (bit for bit)."""

import numpy as np

from selfcal.poses import PoseStore


def windows(rng, n=3000):
    base = np.array([[0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0]])
    d = base[rng.integers(0, 3, n)] + rng.normal(0, 0.01, (n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    norm = 1.0 + rng.normal(0, 3e-4, n)
    bad = rng.random(n) < 0.03  # "still" windows that were not: 2-15 % off
    norm[bad] *= 1 + rng.choice([-1, 1], bad.sum()) * rng.uniform(0.02, 0.15, bad.sum())
    mean = d * norm[:, None]
    t = np.sort(rng.uniform(0, 3 * 86400, n))
    temp = 25 + 5 * np.sin(t / 20000)
    return mean, np.full((n, 3), 3e-3), np.full(n, 200), t, temp


def _assert_same_store(a: PoseStore, b: PoseStore) -> None:
    """Bit for bit: the same cells in the same rows, the same sums (a cell's windows are
    added to it in order, and new cells are appended in the order their first windows
    came, however the windows were split into calls)."""
    assert a.n_gated == b.n_gated
    for name in ("key", "stats", "t_first", "t_last"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_chunking_changes_nothing_and_outliers_are_kept_apart():
    rng = np.random.default_rng(5)
    mean, sd, n, t, temp = windows(rng)
    whole = PoseStore.empty()
    whole.add(mean, sd, n, t, temp)
    for seed in (1, 2):
        parts = PoseStore.empty()
        cuts = np.sort(np.random.default_rng(seed).choice(np.arange(1, len(t)), 200, replace=False))
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(t)]):
            parts.add(mean[a:b], sd[a:b], n[a:b], t[a:b], temp[a:b])
        one = PoseStore.empty()
        for i in range(0, 400):  # window by window, for the first 400
            one.add(mean[i:i + 1], sd[i:i + 1], n[i:i + 1], t[i:i + 1], temp[i:i + 1])
        first = PoseStore.empty()
        first.add(mean[:400], sd[:400], n[:400], t[:400], temp[:400])
        for a, b in ((whole, parts), (first, one)):
            _assert_same_store(a, b)
    assert whole.n_gated > 0 and whole.outlier_twin().sum() > 0


def test_a_shifted_device_clock_changes_no_cell():
    rng = np.random.default_rng(6)
    mean, sd, n, t, temp = windows(rng, 800)
    a, b = PoseStore.empty(), PoseStore.empty()
    a.add(mean, sd, n, t, temp)
    b.add(mean, sd, n, t + 1234.567, temp)  # the insole's clock started earlier
    np.testing.assert_array_equal(np.sort(a.key), np.sort(b.key))
    np.testing.assert_allclose(a.window_counts()[np.argsort(a.key)], b.window_counts()[np.argsort(b.key)])


def test_coarsening_never_merges_across_a_barrier_and_the_barrier_is_kept():
    from selfcal.poses import PoseConfig

    rng = np.random.default_rng(7)
    mean, sd, n, t, temp = windows(rng, 6000)
    cfg = PoseConfig(max_cells=200)  # tight: most cells are coarsened
    tau = t[0] + 48 * cfg.block_s  # a block boundary: no level-0 cell holds both sides
    for barrier in (False, True):
        store = PoseStore.empty(cfg)
        if barrier:
            store.add_barrier(tau)
        store.add(mean, sd, n, t, temp)
        assert store.n_merged > 0 and len(store) <= cfg.max_cells
        if barrier:
            assert store.barriers_s == [tau] and PoseStore.from_json(store.to_json()).barriers_s == [tau]
            assert not store.straddles(tau).any()
        else:
            assert store.straddles(tau).sum() > 0  # without it, coarsening mixes both sides


def test_a_full_store_and_a_cap_on_new_cells_change_nothing_either():
    """With the bound reached many times inside one call, and with ``max_new_cells``,
    the store and the windows taken are those of adding the windows in pieces or one by
    one (the call only ever works on the prefix it can take)."""
    from selfcal.poses import PoseConfig

    cfg = PoseConfig(max_cells=120)  # tight: the bound is reached many times in one call
    for seed in (11, 12):
        rng = np.random.default_rng(seed)
        mean, sd, n, t, temp = windows(rng, 2500)
        whole = PoseStore.empty(cfg)
        out = whole.add(mean, sd, n, t, temp)
        assert out["consumed"] == len(t) and whole.n_merged > 0 and len(whole) <= cfg.max_cells
        parts = PoseStore.empty(cfg)
        cuts = np.sort(rng.choice(np.arange(1, len(t)), 150, replace=False))
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(t)]):
            parts.add(mean[a:b], sd[a:b], n[a:b], t[a:b], temp[a:b])
        assert (whole.n_gated, whole.n_merged, whole.n_seen) == (parts.n_gated, parts.n_merged, parts.n_seen)
        _assert_same_store(whole, parts)

        # max_new_cells: the call stops at the window that opens the k-th new cell, or at
        # the one that takes the store past its bound, the one a window-by-window feed
        # would stop at (the caller's scheduler counts by the store's size, which the bound
        # cuts: it looks again)
        for k in (1, 7, 40):
            capped, single = PoseStore.empty(cfg), PoseStore.empty(cfg)
            capped.add(mean[:900], sd[:900], n[:900], t[:900], temp[:900])
            single.add(mean[:900], sd[:900], n[:900], t[:900], temp[:900])
            got = capped.add(mean[900:], sd[900:], n[900:], t[900:], temp[900:], max_new_cells=k)
            new, taken = 0, 0
            for i in range(900, len(t)):
                one = single.add(mean[i:i + 1], sd[i:i + 1], n[i:i + 1], t[i:i + 1], temp[i:i + 1])
                new += one["new_cells"]
                taken += 1
                if new >= k or one["bounded"]:
                    break
            assert (got["consumed"], got["new_cells"], got["bounded"]) == (taken, new, one["bounded"])
            np.testing.assert_array_equal(np.sort(capped.key), np.sort(single.key))


def test_a_window_whose_statistics_would_overflow_is_not_stored_and_spoils_no_other():
    """A still window with a mean or sd past ~1e154 g (a corrupt packet) is not a pose: it
    is left out, as a NaN one is, and the other windows of its batch are gated as they are
    without it (stored, its inf made its cell's sums NaN, and the gate's running sums of
    every window sorted after it in the batch, which then went ungated)."""
    z = np.array([0.0, 0.0, 1.0])

    def store():
        s = PoseStore.empty()
        s.add(np.tile(z, (5, 1)) * (1 + 1e-4 * np.arange(5))[:, None], np.full((5, 3), 3e-3), np.full(5, 200),
              np.arange(5.0), np.full(5, 25.0))
        return s

    s = store()
    out = s.add(np.array([z * 1.1]), np.array([[1e200] * 3]), np.array([200]), np.array([6.0]), np.array([25.0]))
    assert out["added"] == 0 and out["consumed"] == 1 and np.isfinite(s.stats).all()
    for bad in ([1e200, 0.0, 0.0], [0.0, 0.0, np.nan]):
        a, b = store(), store()
        mean = np.array([z * 1.1, [1.0, 0, 0], bad])
        args = (np.full((3, 3), 3e-3), np.full(3, 200), np.array([6.0, 7, 8]), np.full(3, 25.0))
        got = a.add(mean, *args)
        want = b.add(mean[:2], *(x[:2] for x in args))
        assert (got["added"], got["gated"], got["new_cells"]) == (want["added"], want["gated"], want["new_cells"]) == (2, 1, 2)
        np.testing.assert_array_equal(a.stats, b.stats)


def _same_bits(a, b) -> bool:
    return a.shape == b.shape and np.array_equal(a, b, equal_nan=True) and np.array_equal(np.signbit(a), np.signbit(b))


def test_the_kept_derived_values_are_those_of_the_store_and_only_changed_rows_are_computed():
    """The per-cell values a refit reads (mean direction, mean norm, window noise, dof) are
    kept between refits and only the rows an add changed or appended are computed again:
    after any sequence of adds (cells updated, new cells, the bound's merges and drops)
    they equal, bit for bit, those computed from the whole store."""
    from selfcal.poses import PoseConfig

    for seed, max_cells in ((21, 60), (22, 400), (23, 5000)):
        rng = np.random.default_rng(seed)
        mean, sd, n, t, temp = windows(rng, 1500)
        store = PoseStore.empty(PoseConfig(max_cells=max_cells))
        cuts = np.sort(rng.choice(np.arange(1, len(t)), 300, replace=False))
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(t)]):
            store.add(mean[a:b], sd[a:b], n[a:b], t[a:b], temp[a:b])
            if rng.random() < 0.4:
                kept = store._derived()
                whole = store._derived_from(store.stats)
                assert all(_same_bits(x, y) for x, y in zip(kept, whole))

    # only the rows changed since are computed: one window into an existing cell, one row
    store = PoseStore.empty(PoseConfig())
    mean, sd, n, t, temp = windows(np.random.default_rng(24), 400)
    store.add(mean, sd, n, t, temp)
    store._derived()
    rows_computed = []
    compute = store._derived_from

    def counting(s, direction=True):
        rows_computed.append(len(s))
        return compute(s, direction)

    store._derived_from = counting
    i = int(np.flatnonzero(store._rows_of(store._keys(mean / np.linalg.norm(mean, axis=1, keepdims=True),
                                                         temp, t)) >= 0)[-1])
    store.add(mean[i:i + 1], sd[i:i + 1], n[i:i + 1], t[i:i + 1] + 1.0, temp[i:i + 1])
    rows_computed.clear()
    store._derived()
    assert rows_computed == [1]


def test_a_barrier_does_not_make_the_bound_churn_or_drop_cells():
    """After a bias step (a barrier), cells held at it cannot be coarsened. They must not
    count in the oldest half the bound coarsens: if they did, each pass would merge the
    few other cells in that half, free room for about one new cell, and every new cell
    would pay a whole bound; cells were dropped that coarsening could have kept."""
    from selfcal.poses import PoseConfig

    rng = np.random.default_rng(8)
    mean, sd, n, t, temp = windows(rng, 20000)
    t = t * 10  # 30 days: 720 blocks, most of the old ones coarsened to the top level
    cfg = PoseConfig(max_cells=400)
    passes = {}
    for barrier in (False, True):
        store = PoseStore.empty(cfg)
        if barrier:
            store.add_barrier(float(t[0] - t[0] % cfg.block_s + 120 * cfg.block_s))
        merges = [0]
        merge = store._merge_keys

        def counted(key, merge=merge, merges=merges):
            merges[0] += 1
            merge(key)

        store._merge_keys = counted
        for day in range(30):
            sel = (t >= t[0] + day * 86400.0) & (t < t[0] + (day + 1) * 86400.0)
            store.add(mean[sel], sd[sel], n[sel], t[sel], temp[sel])
        assert len(store) <= cfg.max_cells and store.n_merged > 0
        assert store.n_dropped == 0  # coarsening made room every time
        if barrier:
            assert not store.straddles(store.barriers_s[0]).any()
        passes[barrier] = merges[0]
    assert passes[True] <= 2 * passes[False], passes  # (before the fix: 8503 against 141)


def test_the_gate_in_order_is_the_one_window_at_a_time_loop_bit_for_bit():
    """A cell's windows after a gated one are decided in order against the running sums
    (``_gate_in_order``: one cumsum and one call per gated window). The same store, bit
    for bit, as the plain loop it replaced (a call per window), on batches where up to
    half the windows are outliers."""
    from selfcal.poses import PoseConfig

    def loop(self, start, rows, d):
        out = np.zeros(len(d), dtype=bool)
        run = start.copy()
        for i in range(len(d)):
            out[i] = bool(self._gate_one(run[None, :], d[i: i + 1])[0])
            if not out[i]:
                run += rows[i]
        return out

    cases = ((21, 0.03, 72, None), (22, 0.3, 72, None), (23, 0.5, 72, None), (24, 0.03, 1, 1.0), (25, 0.2, 1, 1.0),
             (26, 0.0, 1, 2.5), (27, 0.01, 1, 2.5))
    for seed, bad_frac, hours, gate_k in cases:
        rng = np.random.default_rng(seed)
        mean, sd, n, t, temp = windows(rng, 4000)
        if hours == 1:  # one block at one temperature: groups of hundreds of windows
            t, temp = t / 72, np.full(len(t), 25.0)
        bad = rng.random(len(t)) < bad_frac
        mean[bad] *= 1 + rng.choice([-1, 1], (bad.sum(), 1)) * rng.uniform(0.02, 0.15, (bad.sum(), 1))
        # and gates so tight (1 and 2.5 sd) that decisions hang on the exact running sums,
        # the looser one with long stretches of windows between two gated ones
        cfg = PoseConfig() if gate_k is None else PoseConfig(gate_k=gate_k, gate_abs_g=1e-6)
        fast, slow = PoseStore.empty(cfg), PoseStore.empty(cfg)
        slow._gate_in_order = loop.__get__(slow)
        calls = [0]
        gate_in_order = fast._gate_in_order

        def counted(*a, f=gate_in_order):
            calls[0] += 1
            return f(*a)

        fast._gate_in_order = counted
        for store in (fast, slow):
            store.add(mean[:1500], sd[:1500], n[:1500], t[:1500], temp[:1500])
            store.add(mean[1500:], sd[1500:], n[1500:], t[1500:], temp[1500:])
        assert calls[0] > 0 and fast.n_gated >= 0.5 * bad.sum()
        np.testing.assert_array_equal(fast.key, slow.key)
        np.testing.assert_array_equal(fast.stats, slow.stats)
        assert fast.n_gated == slow.n_gated


def test_a_window_past_1000_g_is_no_still_pose_and_changes_no_other_gate_decision():
    """A finite but absurd window (|mean| of 1e8 g: a corrupt packet) passed the old
    overflow check. Its cell sorted before +z's, and the gate's running sums (differences of
    one cumsum across the call's cells) lost the +z window before the one decided: a window
    4.4 mg inside its threshold was gated when the three came in one call and not one by
    one. Past 1000 g a window is left out, and the call decides as one window a call does."""
    z = np.array([0.0, 0.0, 1.0])
    for m in (1e3, 1e8, 1e100):
        stores, outs = [], []
        for one_by_one in (False, True):
            s = PoseStore.empty()
            s.add(np.array([z, z]), np.full((2, 3), 3e-3), np.full(2, 200.0), np.array([0.0, 1.0]), np.full(2, 25.0))
            mean = np.array([[-m, 0.0, 0.0], z * 1.009, z * 1.025])
            args = (np.full((3, 3), 3e-3), np.full(3, 200.0), np.array([2.0, 3.0, 4.0]), np.full(3, 25.0))
            parts = [slice(i, i + 1) for i in range(3)] if one_by_one else [slice(0, 3)]
            outs.append([s.add(mean[p], *(x[p] for x in args)) for p in parts])
            stores.append(s)
        assert sum(o["added"] for o in outs[0]) == 2  # the absurd window is not stored
        _assert_same_store(*stores)
        assert stores[0].n_gated == 0  # w2 (25 mg off) is inside its threshold


def test_a_cap_on_new_cells_stops_at_the_window_that_opens_the_last_one_before_invalid_windows():
    """With ``max_new_cells``, the call stops at the window that opens the last cell
    allowed, as one window a call does; an invalid window right after it was consumed with
    it, so the calibrator's clock ran to that window's time before the refit the stop is for."""
    z, x = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    for bad in ([0.0, 0.0, 0.0], [np.nan, 0.0, 1.0], [0.0, 0.0, 1e9]):
        s = PoseStore.empty()
        out = s.add(np.array([z, x, bad]), np.full((3, 3), 3e-3), np.full(3, 200.0), np.array([0.0, 10.0, 20.0]),
                    None, max_new_cells=2)
        assert (out["consumed"], out["added"], out["new_cells"]) == (2, 2, 2), bad


def test_a_window_at_its_gate_threshold_is_decided_as_one_window_a_call_decides_it():
    """A window whose norm is within a few ulps of its gate's threshold (``gate_abs_g`` off
    its cell's running mean norm) after a batch's other cell, sorted before it, whose norms
    are far from 1. Its cell's running sums were differences of one cumsum across the
    batch's cells, which rounded: for 2 of 121 neighbouring norms the batch gated the
    window and one call per window did not (or the other way). They are now added in order
    from the stored row, so every neighbour is decided alike, on every seed."""
    from selfcal import poses

    dirs = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    probe = PoseStore.empty()
    probe.t_origin = 0.0
    order = np.argsort(probe._keys(dirs, np.full(6, 25.0), np.full(6, 10.0)))
    first, last = dirs[order[0]], dirs[order[-1]]  # the other cell sorts before the window's
    sd1, n1, temp1 = np.full((1, 3), 3e-3), np.full(1, 200.0), np.full(1, 25.0)
    for seed in range(8):
        rng = np.random.default_rng(seed)
        stored_d, other_d, d1 = 1e-4 * rng.normal(0, 1, 3), 0.9 + 0.01 * rng.random(60), 1e-4 * rng.normal()

        def store_with_a_cell():
            s = PoseStore.empty()
            for i, dd in enumerate(stored_d):
                s.add((last * (1 + dd))[None], sd1, n1, np.array([float(i)]), temp1)
            return s

        ref = store_with_a_cell()
        ref.add((last * (1 + d1))[None], sd1, n1, np.array([100.0]), temp1)
        row = ref.stats[ref._rows_of(ref.key[-1:])[0]]
        at_threshold = 1.0 + row[poses._SD] / row[poses._NW] + ref.config.gate_abs_g
        norms = [at_threshold]
        for direction in (np.inf, -np.inf):
            x = at_threshold
            for _ in range(60):
                x = np.nextafter(x, direction)
                norms.append(x)
        k = len(other_d) + 2
        sd, n, temp = np.full((k, 3), 3e-3), np.full(k, 200.0), np.full(k, 25.0)
        t = np.r_[np.arange(len(other_d)) + 200.0, 300.0, 301.0]
        gated = 0
        for norm in norms:
            mean = np.vstack([first * (1 + other_d[:, None]), last * (1 + d1), last * norm])
            batch, one = store_with_a_cell(), store_with_a_cell()
            batch.add(mean, sd, n, t, temp)
            for i in range(k):
                one.add(mean[i:i + 1], sd[i:i + 1], n[i:i + 1], t[i:i + 1], temp[i:i + 1])
            _assert_same_store(batch, one)
            gated += one.n_gated
        assert 0 < gated < len(norms)  # the threshold lies among the norms tried


def test_running_sums_are_those_of_adding_the_rows_one_at_a_time():
    """``_running_sums`` (each group's sums before each row, from its start row) equals the
    plain loop bit for bit, with few long groups (a cumsum per group) and many short ones
    (a step per position), rows of mixed magnitudes and signed zeros."""
    from selfcal.poses import _running_sums

    rng = np.random.default_rng(3)
    for sizes in ([1], [7], [1, 1, 1], [40, 2, 1], [2] * 50, [1, 3, 1, 2, 5, 1, 1, 1], list(rng.integers(1, 6, 300))):
        k = int(np.sum(sizes))
        rows = rng.normal(0, 1, (k, 5)) * 10.0 ** rng.integers(-8, 8, (k, 1))
        rows[rng.random((k, 5)) < 0.1] = -0.0
        first = np.zeros(k, dtype=bool)
        first[np.r_[0, np.cumsum(sizes)[:-1]]] = True
        start = rng.normal(0, 1, (k, 5)) * 1e3
        start[0, 0] = -0.0
        want = np.empty_like(rows)
        for i in range(k):
            run = start[i].copy() if first[i] else run + rows[i - 1]
            want[i] = run + 0.0
        for accelerate in ways_of_running_sums():
            got = _running_sums(start, rows, first, accelerate=accelerate)
            np.testing.assert_array_equal(got, want, err_msg=str(accelerate))
            assert not np.signbit(got[got == 0]).any()


def test_the_bound_coarsens_until_every_group_fits_before_it_drops_a_window():
    """15 directions, a bound of 16 cells: all of a month's windows fit once each direction's
    cells are merged. The bound gave up after 8 coarsening passes (a new cell needs up to
    15 to reach its group's oldest) and dropped the oldest cells, which were the largest:
    134 of 4320 windows kept."""
    from selfcal.poses import PoseConfig

    for n_dirs in (10, 15):
        rng = np.random.default_rng(0)
        dirs = rng.standard_normal((n_dirs, 3))
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        k = 2 * 24 * 30  # a window every 30 min for 30 days
        t = 1800.0 * np.arange(k)
        mean = dirs[rng.integers(0, n_dirs, k)] * (1 + 1e-3 * rng.standard_normal((k, 1)))
        store = PoseStore.empty(PoseConfig(max_cells=16))
        for i in range(0, k, 240):
            store.add(mean[i:i + 240], np.full((len(t[i:i + 240]), 3), 2e-3), 40.0, t[i:i + 240], 25.0)
        assert store.n_dropped == 0 and int(store.stats[:, 0].sum()) == k and len(store) <= 16


def test_a_window_with_an_infinite_sd_is_refused_not_stored_as_a_quiet_one():
    for sd, added in ((np.inf, 0), (1e300, 0), (np.nan, 1), (3e-3, 1)):  # NaN: the default sd
        out = PoseStore.empty().add([[0.0, 0.0, 1.0]], [[2e-3, 2e-3, sd]], [40], [0.0])
        assert out["added"] == added, sd


def test_a_saved_store_whose_cells_disagree_is_refused_at_load():
    import pytest

    store = PoseStore.empty()
    store.add(np.tile([0.0, 0.0, 1.0], (3, 1)) + np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]) * 0.7,
              np.full((3, 3), 2e-3), 40.0, np.array([0.0, 10.0, 20.0]), 25.0)
    state = store.to_json()
    assert len(PoseStore.from_json(state)) == len(store) > 1
    for broken in ({**state, "key": state["key"][:-1]}, {**state, "key": [state["key"][0]] * len(state["key"])}):
        with pytest.raises(ValueError, match="pose store"):
            PoseStore.from_json(broken)


def test_the_blocks_an_add_works_in_change_no_cell_and_no_window_taken(monkeypatch):
    """``add`` hands its windows to its steps in blocks (``ADD_BLOCK_WINDOWS``, doubled after
    a block taken whole), not the whole rest of the batch each time. Whatever the block, the
    store, its counters and the windows a capped call takes are those of one block: with the
    bound reached many times in the call, invalid windows (NaN, n = 0) among the others, and
    a cap on new cells."""
    import selfcal.poses as poses_mod
    from selfcal.poses import PoseConfig

    cfg = PoseConfig(max_cells=120)
    for seed in (21, 22):
        rng = np.random.default_rng(seed)
        mean, sd, n, t, temp = windows(rng, 2600)
        n = n.astype(float)
        bad = rng.choice(len(t), 60, replace=False)
        mean[bad[:30]] = np.nan
        n[bad[30:]] = 0.0
        runs = {}
        for block in (10**9, 1, 5, 64, 2048):
            monkeypatch.setattr(poses_mod, "ADD_BLOCK_WINDOWS", block)
            whole = PoseStore.empty(cfg)
            out = whole.add(mean, sd, n, t, temp)
            capped = PoseStore.empty(cfg)
            capped.add(mean[:900], sd[:900], n[:900], t[:900], temp[:900])
            taken = [capped.add(mean[i:], sd[i:], n[i:], t[i:], temp[i:], max_new_cells=k)
                     for i, k in ((900, 7), (1300, 40), (1700, 1))]
            runs[block] = (whole, out, capped, taken)
        ref_whole, ref_out, ref_capped, ref_taken = runs[10**9]
        assert ref_whole.n_merged > 0 and ref_out["bounded"]
        for block, (whole, out, capped, taken) in runs.items():
            assert out == ref_out and taken == ref_taken, block
            for a, b in ((whole, ref_whole), (capped, ref_capped)):
                _assert_same_store(a, b)
                assert (a.n_merged, a.n_dropped, a.n_seen) == (b.n_merged, b.n_dropped, b.n_seen), block


def ways_of_running_sums() -> list:
    """The numpy code (False), and the numba kernel itself when numba is installed."""
    import importlib.util

    if importlib.util.find_spec("numba") is None:
        return [False]
    from selfcal import _sums_jit

    return [False, _sums_jit.running_sums]


def test_the_store_is_the_same_with_and_without_the_sums_kernels(monkeypatch):
    """A store fed 5 000 windows in calls of 37, with the bound reached and invalid windows
    among them: the same cells, sums and counters with the sums' kernels loaded and with
    SELFCAL_NUMBA=0; the kernels pass their first-use check here, and either kernel wrong
    by one ulp in one column is refused (with a warning) and the numpy code runs."""
    import importlib.util
    from types import SimpleNamespace

    import pytest

    from selfcal import sums_numba
    from selfcal.poses import PoseConfig

    if importlib.util.find_spec("numba") is None:
        pytest.skip("numba is not installed (pip install 'selfcal[fast]')")
    monkeypatch.setenv("SELFCAL_NUMBA", "1")
    assert sums_numba.load() and sums_numba.kernels() is not None
    rng = np.random.default_rng(31)
    mean, sd, n, t, temp = windows(rng, 5000)
    n = n.astype(float)
    n[rng.choice(len(n), 40, replace=False)] = 0.0
    stores = []
    for switch in ("1", "0"):
        monkeypatch.setenv("SELFCAL_NUMBA", switch)
        assert (sums_numba.kernels() is not None) == (switch == "1")
        store = PoseStore.empty(PoseConfig(max_cells=150))
        for i in range(0, len(t), 37):
            store.add(mean[i:i + 37], sd[i:i + 37], n[i:i + 37], t[i:i + 37], temp[i:i + 37])
        stores.append(store)
    _assert_same_store(*stores)
    assert stores[0].n_merged > 0 and stores[0].n_gated > 0
    assert (stores[0].n_merged, stores[0].n_dropped, stores[0].n_seen) == (
        stores[1].n_merged, stores[1].n_dropped, stores[1].n_seen)

    from selfcal import _sums_jit

    real = sums_numba._load()

    def off(kernel):
        def wrong(*args):
            kernel(*args)
            out = args[-1]
            out[:, 2] = np.nextafter(out[:, 2], np.inf)
        return wrong

    assert sums_numba._same_as_numpy(real)
    for name in ("running_sums", "sum_by_group"):
        broken = SimpleNamespace(**{**vars(real), name: off(getattr(real, name))})
        assert not sums_numba._same_as_numpy(broken), name
        monkeypatch.setenv("SELFCAL_NUMBA", "1")
        monkeypatch.setattr(_sums_jit, name, getattr(broken, name))
        monkeypatch.setattr(sums_numba.SUMS, "_found", [])
        with pytest.warns(RuntimeWarning, match="sums' numba kernels gave other results"):
            assert not sums_numba.load()
        assert sums_numba.kernels() is None
        monkeypatch.setattr(_sums_jit, name, getattr(real, name))


def test_group_sums_are_those_of_np_add_at_for_numpy_and_the_kernel():
    """``sum_by_group`` is ``np.add.at`` into zeros bit for bit, by the numpy code and by the
    kernel: groups in any order, empty groups, signed zeros, one row and many."""
    from selfcal.groupsum import sum_by_group

    ways = [False]
    import importlib.util

    if importlib.util.find_spec("numba") is not None:
        from selfcal import _sums_jit

        ways.append(_sums_jit.sum_by_group)
    rng = np.random.default_rng(5)
    for k, n_groups, cols in ((1, 1, 3), (5, 9, 2), (300, 40, 17), (2000, 7, 5)):
        group = rng.integers(0, n_groups, k)
        values = rng.normal(0.0, 1.0, (k, cols)) * 10.0 ** rng.integers(-8, 8, (k, 1))
        values[rng.random((k, cols)) < 0.1] = -0.0
        want = np.zeros((n_groups, cols))
        np.add.at(want, group, values)
        for accelerate in ways:
            got = sum_by_group(group, values, n_groups, accelerate=accelerate)
            np.testing.assert_array_equal(got, want, err_msg=str(accelerate))
            assert np.array_equal(np.signbit(got), np.signbit(want))

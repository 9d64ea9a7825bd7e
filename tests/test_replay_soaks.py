"""``selfcal replay --soaks``: what thermal soaks bring to the temperature terms, online."""

import json

import numpy as np
import pytest

from selfcal.cli import main
from selfcal.config import load_config
from selfcal.replay import effect_summary, replay
from selfcal.soak import find_soaks

MODEL = "affine9+temperature_bias"


def test_without_soaks_drops_exactly_the_soak_windows():
    cfg = load_config(None)
    kw = dict(days=2.0, refit_every_days=0, seed=3, config=cfg, effects=("temperature_bias",), model=MODEL)
    with_ = replay(**kw)
    without = replay(soaks=False, **kw)
    assert with_["soaks"] == {"dropped": False, "n_soaks": 0, "n_windows": 0}
    assert without["soaks"]["n_soaks"] > 0  # an insole taken off cools in its shoe every evening
    assert without["n_still_windows"] == with_["n_still_windows"] - without["soaks"]["n_windows"]
    # every row carries the effect terms, and the summary scores them against the truth
    for out in (with_, without):
        assert set(out["effect_summary"]) == {"tbx", "tby", "tbz"}
        for name, e in out["effect_summary"].items():
            assert e["true"] == pytest.approx(out["truth"]["effects"][name])
            assert e["final_error"] == pytest.approx(e["final"] - e["true"])


def test_soak_windows_found_in_the_replayed_windows_are_gone():
    """Dropping is by find_soaks on the still windows, the real-world rule (no simulator label)."""
    cfg = load_config(None)
    out = replay(days=1.0, refit_every_days=0, seed=5, config=cfg, effects=("temperature_bias",), model=MODEL,
                 soaks=False)
    assert out["soaks"]["n_soaks"] > 0
    assert out["soaks"]["n_windows"] >= out["soaks"]["n_soaks"] * 5


def test_effect_summary_first_determined_day_and_error():
    rows = [
        {"day": 0.5, "effect_terms": {"tbz": {"est": 0.0, "sd": 1e-3, "determined": False}}},
        {"day": 1.0, "effect_terms": {"tbz": {"est": 0.9e-3, "sd": 0.2e-3, "determined": True}}},
        {"day": 2.0, "effect_terms": {"tbz": {"est": 1.1e-3, "sd": 0.05e-3, "determined": True}}},
    ]
    s = effect_summary(rows, {"tbz": 1.0e-3})["tbz"]
    assert s["first_determined_day"] == 1.0
    assert s["final_error"] == pytest.approx(0.1e-3)
    assert s["final_error_sd"] == pytest.approx(2.0)
    never = effect_summary(rows[:1], {"tbz": 1.0e-3})["tbz"]
    assert never["first_determined_day"] is None


def test_cli_soaks_both_prints_the_comparison(capsys):
    assert main(["replay", "--effects", "temperature_bias", "--model", MODEL, "--days", "1.5",
                 "--refit-every-days", "0", "--devices", "2", "--workers", "1", "--soaks", "both",
                 "--no-progress", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out["summary"]) == {"tbx", "tby", "tbz"}
    assert len(out["table"]) == 2 * 3
    for row in out["table"]:
        assert row["soaks_dropped"] > 0
        for label in ("with", "without"):
            assert np.isfinite(row[label]["final_error"])
    assert main(["replay", "--effects", "temperature_bias", "--model", MODEL, "--days", "1.5",
                 "--refit-every-days", "0", "--devices", "2", "--workers", "1", "--soaks", "both",
                 "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "tbz with soaks" in text and "tbz without soaks" in text


def test_soaks_without_at_samples_level_is_a_clear_error(capsys):
    assert main(["replay", "--days", "1", "--level", "samples", "--soaks", "without", "--no-progress"]) != 0
    assert "--level poses" in capsys.readouterr().err


def test_find_soaks_agrees_with_the_simulator_off_foot_label():
    """The soaks find_soaks names in simulated wear are mostly the off-foot windows (the
    insole lying in its shoe), so 'without soaks' removes what the simulator means by soaks."""
    from selfcal.sim import SimConfig, Simulation
    from selfcal.sim.wearer import OFF

    cfg = load_config(None)
    sim = Simulation(SimConfig.from_section(cfg["sim"]).with_effects(["temperature_bias"]),
                     np.random.default_rng(7), days=2.0, seed=7)
    p = sim.poses()
    o = np.argsort(p.t_s)
    runs = find_soaks(p.t_s[o], p.mean_g[o], p.temp_c[o])
    in_soak = np.zeros(len(o), bool)
    for r in runs:
        in_soak[r] = True
    off = p.activity[o] == OFF
    assert in_soak.sum() > 0
    assert np.mean(off[in_soak]) > 0.8

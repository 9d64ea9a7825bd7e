"""Online model selection: the calibrator switches in an effect its poses support, publishes the
switch as a version with its reason and gain, drops an effect that stops paying, and leaves
effect-free devices alone."""

import copy

import numpy as np
import pytest

from selfcal.calibrator import OnlineCalibrator
from selfcal.config import load_config
from selfcal.errors import InputError
from selfcal.replay import replay
from selfcal.selection import SelectionConfig
from selfcal.sim import SimConfig, Simulation


def _poses(seed: int, days: float, effects=()):
    cfg = load_config(None)
    sim_cfg = SimConfig.from_section(cfg["sim"])
    if effects:
        sim_cfg = sim_cfg.with_effects(list(effects))
    sim = Simulation(sim_cfg, np.random.default_rng(seed), days=days, seed=seed)
    p = sim.poses()
    keep = np.all(p.sd_g <= 0.010, axis=1)
    o = np.argsort(p.t_s[keep], kind="stable")
    idx = np.flatnonzero(keep)[o]
    return cfg, sim, (p.mean_g[idx], p.sd_g[idx], p.n[idx], p.t_s[idx] + p.duration_s[idx] / 2, p.temp_c[idx])


@pytest.mark.parametrize("seed", [0, 3])
def test_a_temperature_effect_is_switched_in_and_published_with_its_reason(seed):
    out = replay(days=9, seed=seed, config=load_config(None), effects=("temperature_bias",))
    assert out["model_final"] == "affine9+temperature_bias", out["model_switches"]
    sw = out["model_switches"][0]
    assert sw["change"] == "added" and sw["effect"] == "temperature_bias"
    assert sw["heldout_z"] >= 3.0 and sw["heldout_rms_mg_after"] < sw["heldout_rms_mg_before"]
    row = next(r for r in out["refits"] if r.get("model_change"))
    assert row["published"] and row["mode"] == "model_switch"
    # after the switch the effect's terms are estimated and honest
    for name, e in out["effect_summary"].items():
        assert e["final_error_sd"] <= 3.0, (name, e)


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_no_switch_on_effect_free_devices(seed):
    out = replay(days=14, seed=seed, config=load_config(None), effects=())
    assert out["model_switches"] == [] and out["model_final"] == "affine9"


def test_the_switch_is_a_published_version_that_names_the_change():
    cfg, _, poses = _poses(4, 6.0, ("temperature_bias",))
    cal = OnlineCalibrator(cfg, "affine9")
    events = cal.feed_poses(*poses)
    switch = [e for e in events if e.get("mode") == "model_switch"]
    assert switch, [e.get("mode") for e in events]
    # early on, flat poses may not tell a temperature bias from a temperature scale: the
    # better predictor goes in first and a rival that stops paying is dropped again
    for e in switch:
        c = e["calibration"]
        assert e["published"] and c["model_change"]["to_model"] == c["model"]
        assert c["model_change"]["change"] in ("added", "dropped")
    assert switch[0]["calibration"]["model_change"]["from_model"] == "affine9"
    assert len(switch) <= 3
    c = switch[-1]["calibration"]
    assert c["model"] == "affine9+temperature_bias"
    assert {"tbx", "tby", "tbz"} <= set(c["params"]) and {"tbx", "tby", "tbz"} <= set(c["std"])
    assert cal.current["calibration"]["model"] == "affine9+temperature_bias"
    assert any("temperature_bias added" in e["message"] for e in switch)
    # the state keeps the model and why
    back = OnlineCalibrator.from_json(cal.to_json())
    assert back.model.name == "affine9+temperature_bias"
    assert back.selection["added"] == ["temperature_bias"]
    assert back.to_json() == cal.to_json()


def test_an_effect_that_stops_paying_is_dropped():
    """A device whose temperature effect selection had added, on data without one."""
    cfg, _, poses = _poses(5, 4.0, ())
    cal = OnlineCalibrator(cfg, "affine9+temperature_bias")
    cal.selection["added"] = ["temperature_bias"]
    events = cal.feed_poses(*poses)
    switch = [e for e in events if e.get("mode") == "model_switch"]
    assert switch, "the unpaid effect was kept"
    change = switch[0]["calibration"]["model_change"]
    assert change["change"] == "dropped" and change["to_model"] == "affine9"
    assert cal.model.name == "affine9" and cal.selection["added"] == []


def test_an_effect_the_operator_chose_is_never_dropped():
    cfg, _, poses = _poses(5, 4.0, ())
    cal = OnlineCalibrator(cfg, "affine9+temperature_bias")  # configured, not added by selection
    events = cal.feed_poses(*poses)
    assert not [e for e in events if e.get("mode") == "model_switch"]
    assert cal.model.name == "affine9+temperature_bias"


def test_selection_can_be_switched_off():
    cfg, _, poses = _poses(4, 6.0, ("temperature_bias",))
    cfg = copy.deepcopy(cfg)
    cfg["selection"] = {"enabled": False}
    cal = OnlineCalibrator(cfg, "affine9")
    cal.feed_poses(*poses)
    assert cal.model.name == "affine9" and cal.selection["last_check_t_s"] is None


def test_unknown_candidate_is_a_clear_error():
    with pytest.raises(InputError, match="candidates: unknown"):
        SelectionConfig.from_section({"candidates": ["temperature_bias", "hysteresis"]})


def test_replay_fleet_prints_how_many_devices_switched_and_when(capsys):
    from selfcal.cli import main

    assert main(["replay", "--effects", "temperature_bias", "--days", "9", "--devices", "2", "--workers", "1",
                 "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "model selection: 2/2 devices switched (median day of the first switch 6.00)" in out, out
    assert "affine9+temperature_bias x2" in out

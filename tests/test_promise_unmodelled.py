"""A version's promise covers the sensor as it may be, not only the model it fits.

* **Effects the model lacks.** ``predicted_sphere_rms_mg`` includes what the ``[selection]``
  candidates the model lacks could add over the sphere, at their datasheet size as far as
  the cells do not determine them (``[scheduler] predict_unmodelled``). A quadratic
  nonlinearity is invisible on an insole's poses near ±1 g (there it is an offset), so
  model selection never names it; the calibrator published ``calibrated`` versions
  predicting 0.2-0.9 mg whose true whole-sphere error was 2.6-4.4 mg.
* **A flagged offset jump.** A version whose recent cells disagree with the model (a bias
  step not yet named) is ``provisional`` and predicts the jump those cells show; the next
  refit, hours later with too few cells of its own to test, counts from where the flagged
  check counted. It used to publish the same disagreement as ``calibrated``.

Scored as ``selfcal replay --recording`` scores a simulated file: every version against
the truth ``selfcal simulate`` wrote beside it.
"""

import numpy as np
import pytest

from selfcal.cli import main
from selfcal.config import load_config
from selfcal.pipeline import calibrate_path, published_versions
from selfcal.scoring import PROMISE_RATIO, PROMISE_SLACK_MG, TruthScorer, load_truth, truth_path


def _scored_versions(tmp_path, seed: int, days: float, effects: str, predict_unmodelled: bool = True,
                     toml: str | None = None, candidates: list[str] | None = None) -> list[dict]:
    out = tmp_path / f"wear_{seed}.csv"
    argv = ["simulate", "--days", str(days), "--seed", str(seed), "--kind", "poses", "--effects", effects,
            "--out", str(out)]
    config_path = None
    if toml:
        config_path = tmp_path / "sim.toml"
        config_path.write_text(toml)
        argv += ["--config", str(config_path)]
    assert main(argv) == 0
    cfg = load_config(config_path)
    cfg["scheduler"] = dict(cfg.get("scheduler", {}), predict_unmodelled=predict_unmodelled)
    if candidates is not None:
        cfg["selection"] = dict(cfg.get("selection", {}), candidates=candidates)
    calibrations = published_versions(calibrate_path(out, "affine9", cfg))
    rows = TruthScorer(load_truth(truth_path(out)), "affine9").score_all(calibrations)
    return [dict(row, calibration=c) for row, c in zip(rows, calibrations)]


def _broken(versions: list[dict]) -> list[tuple]:
    return [(v["version"], v["status"], round(v["true_mg"], 2), round(v["predicted_mg"], 2)) for v in versions
            if v["true_mg"] > PROMISE_RATIO * v["predicted_mg"] + PROMISE_SLACK_MG]


@pytest.mark.parametrize("seed", [1001, 1005, 1007])
def test_every_version_keeps_its_promise_with_a_nonlinearity_no_pose_tells_apart(tmp_path, seed):
    versions = _scored_versions(tmp_path, seed, 5, "scale_nonlinearity")
    assert versions and _broken(versions) == []
    assert all(v["calibration"]["model"] == "affine9" for v in versions)  # never named: it holds without it


def test_a_version_flagged_for_an_offset_jump_predicts_it_and_the_next_refit_does_not_clear_it(tmp_path):
    """The offset jumps by 1-2 mg on day 6 of 12; the unmodelled term off, so that what is
    tested is the flag alone. The old code flagged the day-6.04 version but predicted
    0.49 mg against a true 1.37, and the refit 6 h later (7 new cells) was ``calibrated``
    with the same estimate."""
    toml = "[sim.effects.bias_step]\nat_day = 6.0\n"
    versions = _scored_versions(tmp_path, 1003, 12, "bias_step", predict_unmodelled=False, toml=toml)
    assert _broken(versions) == []
    flagged = [i for i, v in enumerate(versions) if v["calibration"].get("recent_jump")]
    assert flagged, "the recent-cells check never fired: the test does not exercise it"
    for i in flagged:
        c = versions[i]["calibration"]
        assert c["status"] == "provisional" and "a bias step?" in c["status_reason"]
        assert c["recent_jump"]["chi2"] > c["recent_jump"]["threshold"] and c["recent_jump"]["sphere_rms_mg"] > 0


def test_the_unmodelled_term_is_what_the_missing_candidates_add(tmp_path):
    """``unmodelled`` names the candidates the model lacks and the whole-sphere error they
    add (what the cells leave open and what they say the effects are, in quadrature);
    ``predicted_sphere_rms_mg`` is its sum in quadrature with the model's own. A
    model with every candidate has nothing to add; switched off, the prediction is the
    model's alone."""
    from posegen import poses_from_truth, random_truth, spread_directions

    from selfcal.calibrator import OnlineCalibrator
    from selfcal.models import ErrorModel

    rng = np.random.default_rng(4)
    truth = random_truth(rng)
    n = 400
    d = spread_directions(rng, n)
    poses = poses_from_truth(rng, ErrorModel("affine9"), truth, d, sample_sd_g=3e-3, count=200,
                             t_s=600.0 * np.arange(n))
    temp = 25.0 + 8.0 * np.sin(np.arange(n) / 40.0)
    every = "affine9+temperature_bias+temperature_scale+time_drift_bias+scale_nonlinearity+temperature_cross"
    base = {k: v for k, v in load_config().items() if k not in ("service", "gateway")}
    for model, predict in (("affine9", True), ("affine9", False), (every, True)):
        cfg = dict(base, scheduler=dict(base.get("scheduler", {}), predict_unmodelled=predict),
                   selection=dict(base.get("selection", {}), enabled=False))
        cal = OnlineCalibrator(config=cfg, model=model)
        cal.feed_poses(poses.mean, poses.sd, poses.count, poses.t_s, temp)
        c = cal.calibration()
        assert c is not None
        un = c["unmodelled"]
        if not predict or model == every:
            assert un == {"effects": [], "sphere_rms_mg": 0.0, "undetermined_mg": 0.0, "determined_mg": 0.0}
            assert c["predicted_sphere_rms_mg"] == c["predicted_sphere_rms_mg_model"]
        else:
            assert un["effects"] == ["temperature_bias", "temperature_scale", "time_drift_bias", "scale_nonlinearity",
                                     "temperature_cross"]
            assert un["sphere_rms_mg"] > 0 and un["undetermined_mg"] > 0 and un["determined_mg"] >= 0
            assert un["sphere_rms_mg"] == pytest.approx(np.hypot(un["undetermined_mg"], un["determined_mg"]), rel=1e-12)
            assert c["predicted_sphere_rms_mg"] == pytest.approx(np.hypot(c["predicted_sphere_rms_mg_model"],
                                                                           un["sphere_rms_mg"]), rel=1e-12)


@pytest.mark.parametrize("seed", [1002, 1003])
def test_a_sensor_without_the_effect_is_not_said_to_have_it(tmp_path, seed):
    """No effect in the simulated insole, the nonlinearity the one candidate: what the
    cells say it is (``determined_mg``) stays within what they leave open of it
    (``undetermined_mg``), and every version keeps its promise. Taking the extended
    estimate as one Gauss-Newton step from the fit read the fit's remainder (it is
    stationary only to its tolerance, in a noise model whose sigma depends on the
    parameters) as a nonlinearity of 10-100 mg/g^2, on ±1 g poses nearly an offset:
    2-240 mg over the sphere on seed 1002 against a true error of 0.6-5 mg."""
    versions = _scored_versions(tmp_path, seed, 8, "none", candidates=["scale_nonlinearity"])
    assert len(versions) >= 8 and _broken(versions) == []
    parts = [(v["version"], v["calibration"]["unmodelled"]) for v in versions]
    said = [(version, round(u["determined_mg"], 2), round(u["undetermined_mg"], 2)) for version, u in parts
            if u["determined_mg"] > u["undetermined_mg"]]
    assert said == []


def test_a_nonlinearity_the_poses_see_is_the_error_it_makes():
    """Poses spread over the sphere see a 3 mg/g^2 nonlinearity: ``determined_mg`` is the
    whole-sphere error the model without it makes (0.8 mg, the truth is known), within a
    fifth; the model's own covariance says ~0.1 mg."""
    from posegen import poses_from_truth, random_truth, spread_directions

    from selfcal.calibrator import OnlineCalibrator
    from selfcal.models import ErrorModel

    for seed in (5, 6, 7):
        rng = np.random.default_rng(seed)
        ext = ErrorModel("affine9+scale_nonlinearity")
        truth = ext.extend_theta(random_truth(rng), ErrorModel("affine9"))
        truth[ext.index("scale_nonlinearity")] = 3e-3 * rng.choice([-1.0, 1.0], 3)
        n = 600
        poses = poses_from_truth(rng, ext, truth, spread_directions(rng, n), sample_sd_g=3e-3, count=200,
                                 t_s=600.0 * np.arange(n))
        base = {k: v for k, v in load_config().items() if k not in ("service", "gateway")}
        cfg = dict(base, scheduler=dict(base["scheduler"], predict_unmodelled=True),
                   selection=dict(base["selection"], enabled=False, candidates=["scale_nonlinearity"]))
        cal = OnlineCalibrator(config=cfg, model="affine9")
        cal.feed_poses(poses.mean, poses.sd, poses.count, poses.t_s, None)
        c = cal.calibration()
        # the version's own error over the sphere: noise-free readings of the nonlinear truth
        sphere = poses_from_truth(np.random.default_rng(0), ext, truth, spread_directions(np.random.default_rng(1), 2000),
                                  sample_sd_g=0.0, count=1).mean
        a = (sphere - np.asarray(c["offset"], float)) @ np.asarray(c["matrix"], float).T
        true_mg = float(np.sqrt(np.mean((np.linalg.norm(a, axis=1) - 1.0) ** 2)) * 1e3)
        said = c["unmodelled"]["determined_mg"]
        assert c["unmodelled"]["effects"] == ["scale_nonlinearity"]
        # (the model's own prediction, ~0.1 mg, would break its promise)
        assert true_mg > 3 * c["predicted_sphere_rms_mg_model"]
        assert said == pytest.approx(true_mg, rel=0.2), (seed, said, true_mg)


def test_the_jump_of_a_flag_is_the_one_after_it_happened_not_its_average_over_the_recent_cells():
    """A jump 80 % of the way through the recent cells: :func:`selfcal.steps.latest_jump`
    finds where and sizes it (within 4 sd); the least-squares jump over every recent cell
    (what a flagged version predicted before) is a fifth of it. Offsets in g."""
    from selfcal.steps import jump_fit, latest_jump

    rng = np.random.default_rng(11)
    n, sigma = 3000, 2e-3
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    t = np.sort(rng.uniform(0.0, 10.0, n)) * 86400.0
    step = np.array([1.5e-3, -1.0e-3, 2.0e-3])
    after = t > 9.6 * 86400.0
    recent = t > 8.0 * 86400.0
    jw = -u / sigma  # d(norm residual)/d(offset), whitened
    rw = (after * (u @ step) + sigma * rng.standard_normal(n)) / sigma
    q = np.zeros((n, 0))  # no model columns to project out
    tau, jump, cov = latest_jump(jw, q, rw, t, recent)
    assert 9.5 * 86400 < tau < 9.7 * 86400
    z = (jump - (-step)) / np.sqrt(np.diag(cov))  # (a jump of the offset shifts the norm residual by -u.jump)
    assert np.all(np.abs(z) < 4), z
    _, diluted, _ = jump_fit(jw, q, rw, recent)
    assert np.linalg.norm(diluted) < 0.35 * np.linalg.norm(step)


def test_the_versions_of_the_hours_after_a_late_step_keep_their_promise(tmp_path):
    """A 1-2 mg offset step on day 10 of 12 (wearer 1000): the versions flagged for it
    (``recent_jump``) predicted 0.11, 0.27 and 0.46 mg against a true 1.34-1.38, the jump
    of every cell since the last version that agreed, most of them from before it. (Its
    version 5, on day 0.42 from 128 cells, is 2.5x beyond its promise: the early fits'
    own miss, not the step's.)"""
    versions = _scored_versions(tmp_path, 1000, 12, "bias_step", predict_unmodelled=False)
    flagged = [v for v in versions if v["calibration"].get("recent_jump")]
    assert len(flagged) >= 2
    assert _broken([v for v in versions if v["t_s"] >= 10 * 86400.0]) == []

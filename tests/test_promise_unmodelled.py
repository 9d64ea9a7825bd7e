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
                     toml: str | None = None) -> list[dict]:
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
    add; ``predicted_sphere_rms_mg`` is its sum in quadrature with the model's own. A
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
            assert un == {"effects": [], "sphere_rms_mg": 0.0}
            assert c["predicted_sphere_rms_mg"] == c["predicted_sphere_rms_mg_model"]
        else:
            assert un["effects"] == ["temperature_bias", "temperature_scale", "time_drift_bias", "scale_nonlinearity",
                                     "temperature_cross"]
            assert un["sphere_rms_mg"] > 0
            assert c["predicted_sphere_rms_mg"] == pytest.approx(np.hypot(c["predicted_sphere_rms_mg_model"],
                                                                           un["sphere_rms_mg"]), rel=1e-12)

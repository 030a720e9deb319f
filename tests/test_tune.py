"""The tuner finds a known optimum; the tuning command writes specs the registry accepts."""

import json

import numpy as np
import pytest
from uwb_env.agents.registry import make_policy
from uwb_env.training.tune import Args, load_tuned, tune, tune_family


def test_continuous_optimum_between_grid_points():
    calls = []

    def objective(points):
        calls.append(list(points))
        return [-(p - 0.137) ** 2 for p in points]

    result = tune_family("threshold", objective, refine_rounds=6)
    assert result.best_value == pytest.approx(0.137, abs=0.004)
    assert result.best_spec.startswith("threshold:0.13")
    assert len(calls) > 1  # refinement ran after the grid


def test_integer_optimum_and_noise_free_plateau():
    result = tune_family("fixed", lambda ps: [-abs(p - 11) for p in ps], refine_rounds=5)
    assert result.best_value == 11 and result.best_spec == "fixed:11"
    # A monotone objective ends at the grid's edge, not in between.
    assert tune_family("fixed", lambda ps: list(ps)).best_spec == "fixed:300"


def test_tune_command_on_short_episodes(tmp_path):
    out = tmp_path / "tuned.json"
    record = tune(Args(families=["fixed", "threshold"], seeds=2, max_cycles=40, workers=1, out=str(out),
                       refine_rounds=0, progress=False))
    saved = json.loads(out.read_text())
    assert saved["tuned"] == record["tuned"] and saved["best_tuned_heuristic"] in saved["tuned"].values()
    assert set(saved["tuned"]) == {"fixed", "threshold"}
    for spec in saved["tuned"].values():
        make_policy(spec)
    best = saved["families"][saved["best_tuned_heuristic"].partition(":")[0]]
    assert best["best_return"] == max(f["best_return"] for f in saved["families"].values())
    assert best["best_return"] == max(best["evaluated"].values())
    assert saved["validation_seeds"][0] == 500_000
    assert load_tuned(str(out))["tuned"] == saved["tuned"]
    assert np.isfinite(best["best_return_sem"])
    with pytest.raises(ValueError, match="families"):
        tune(Args(families=["nope"], out=""))

import csv
import json

import numpy as np
import pytest
from uwb_env.agents.registry import POLICIES, PolicySpecError, make_policy
from uwb_env.training.evaluate import EVAL_SEED_BASE, Args, format_table, main, sweep_specs

from uwb_env.cli import main as cli_main


def test_registry_builds_every_baseline_and_rejects_bad_specs():
    for name in POLICIES:
        if name not in ("learned", "rllib", "rollout"):  # these need a model or a base
            assert make_policy(name).act is not None
    assert make_policy("rollout:20@never").act is not None
    with pytest.raises(PolicySpecError, match="base scheduler"):
        make_policy("rollout")
    assert make_policy("fixed:7").interval_steps == 7
    assert make_policy("fixed_s:1.0", dt_s=0.2).interval_steps == 5
    assert make_policy("oracle").uses_ground_truth
    with pytest.raises(PolicySpecError, match="'bogus'"):
        make_policy("bogus:3")
    with pytest.raises(PolicySpecError, match="threshold:-1"):
        make_policy("threshold:-1")
    with pytest.raises(PolicySpecError, match="model path"):
        make_policy("learned")


def test_harness_on_a_tiny_run_writes_sane_files(tmp_path):
    out = tmp_path / "ev"
    args = Args(policies=["fixed:5", "never", "oracle:0.2"], seeds=2, max_cycles=40, sweep=False,
                workers=1, out=str(out), progress=False, tuned="none")
    results = main(args)
    rows = {r["policy"]: r for r in results["summary"]}
    assert set(rows) == {"fixed:5", "never", "oracle:0.2"}
    assert results["seeds"] == [EVAL_SEED_BASE, EVAL_SEED_BASE + 1]  # held-out seeds
    # fixed:5 at dt 0.2 s starts a round every 5 steps = 1 s (rounds last < 5 steps): 60 per minute
    assert rows["fixed:5"]["calibrations_per_min"] == pytest.approx(60.0)
    assert rows["never"]["calibrations_per_min"] == 0 and rows["never"]["fraction_calibrating"] == 0
    assert rows["fixed:5"]["mean_anchor_error_m"] < rows["never"]["mean_anchor_error_m"]
    assert rows["oracle:0.2"]["uses_ground_truth"] and not rows["never"]["uses_ground_truth"]
    for r in rows.values():
        assert 0 <= r["median_tag_error_m"] <= r["p95_tag_error_m"]
        assert np.isfinite(r["return"]) and r["return"] <= 0
    with open(out / "episodes.csv") as f:
        episodes = list(csv.DictReader(f))
    assert len(episodes) == 3 * 2
    summary = json.loads((out / "summary.json").read_text())
    assert {r["policy"] for r in summary["summary"]} == set(rows)
    for name in ("error_over_time.png", "boxplot.png", "tradeoff.png"):
        assert (out / name).stat().st_size > 1000
    assert "oracle:0.2 (GT)" in format_table(results["summary"])


def test_parallel_workers_give_the_same_numbers_as_one_process(tmp_path):
    common = dict(policies=["threshold:0.1"], seeds=2, max_cycles=30, sweep=False, out=None, progress=False)
    one = main(Args(workers=1, **common))["summary"][0]
    two = main(Args(workers=2, **common))["summary"][0]
    assert one == two


def test_sweep_specs_cover_both_families():
    specs = sweep_specs()
    assert any(s.startswith("fixed:") for s in specs) and any(s.startswith("threshold:") for s in specs)
    for s in specs:
        make_policy(s)


def test_cli_evaluate_prints_the_table_and_rejects_a_bad_policy(tmp_path, capsys):
    assert cli_main(["evaluate", "--policies", "fixed:10", "--seeds", "1", "--max-cycles", "20", "--no-sweep",
                     "--workers", "1", "--out", str(tmp_path), "--no-plots", "--quiet"]) == 0
    assert "fixed:10" in capsys.readouterr().out
    assert cli_main(["evaluate", "--policies", "nope", "--seeds", "1", "--no-sweep", "--out", str(tmp_path)]) == 2
    assert "unknown name 'nope'" in capsys.readouterr().err


def test_several_scenarios_each_get_their_folder_and_one_csv(tmp_path):
    from pathlib import Path

    scenarios = sorted(str(p) for p in (Path(__file__).parents[1] / "training" / "scenarios").glob("*.yml"))
    assert len(scenarios) >= 3
    out = tmp_path / "sc"
    results = main(Args(policies=["fixed:10"], seeds=1, max_cycles=15, sweep=False, workers=1, out=str(out),
                        plots=False, progress=False, scenarios=scenarios[:2]))
    assert set(results) == {Path(s).stem for s in scenarios[:2]}
    for name in results:
        assert (out / name / "summary.json").exists()
    with open(out / "scenarios.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["scenario"] for r in rows] == [Path(s).stem for s in scenarios[:2]]


def test_a_model_that_does_not_fit_the_scenario_is_skipped_there_and_refused_alone(tmp_path, capsys):
    pytest.importorskip("stable_baselines3", reason="learned policies need the train extra")
    from pathlib import Path

    eight = str(Path(__file__).parents[1] / "training" / "scenarios" / "eight_anchors.yml")
    base = dict(policies=["learned:ppo_scheduler", "never"], seeds=1, max_cycles=20, sweep=False, workers=1,
                plots=False, progress=False)
    with pytest.raises(ValueError, match=r"learned:ppo_scheduler.*\(80,\).*\(40,\)"):
        main(Args(**base, config=eight, out=None))
    results = main(Args(**base, scenarios=[eight], out=str(tmp_path)))
    assert [r["policy"] for r in results["eight_anchors"]["summary"]] == ["never"]
    assert "skipping learned:ppo_scheduler" in capsys.readouterr().out


def test_suite_covers_the_protocol_scenarios_with_disjoint_seed_ranges(tmp_path):
    from uwb_env.training.suite import load_suite

    from uwb_env.config import EnvConfig

    suite = load_suite()
    assert {"paper", "default", "stop_and_go", "harsh_radio", "fast_robots", "low_drift", "dt_0.1",
            "five_anchors", "eight_anchors", "three_d"} <= set(suite)
    for name, sc in suite.items():
        EnvConfig.from_dict({**sc["config"], "max_cycles": sc["max_cycles"]})  # every scenario is a valid config
        ranges = sorted(sc["seeds"].values())
        assert all(a[1] < b[0] for a, b in zip(ranges, ranges[1:], strict=False)), name
    bad = tmp_path / "bad.yml"
    bad.write_text("seeds: {training: [0, 10], validation: [5, 20], test: [30, 40]}\nscenarios: {x: {config: {}}}\n")
    with pytest.raises(ValueError, match="overlap"):
        load_suite(str(bad))


def test_suite_run_writes_tables_and_a_profile(tmp_path, capsys):
    out = tmp_path / "suite"
    result = main(Args(policies=["fixed:5", "never"], seeds=3, workers=1, out=str(out), progress=False,
                       suite="default", suite_scenarios=["default", "five_anchors"]))
    assert set(result["per_scenario"]) == {"default", "five_anchors"}
    assert result["per_scenario"]["default"]["seeds"] == [1_000_000, 1_000_001, 1_000_002]
    for name in ("suite_per_scenario.csv", "suite_aggregate.csv", "performance_profile.png"):
        assert (out / name).stat().st_size > 100
    with open(out / "suite_per_scenario.csv") as f:
        rows = list(csv.DictReader(f))
    assert {(r["scenario"], r["policy"]) for r in rows} == {(s, p) for s in ("default", "five_anchors")
                                                             for p in ("fixed:5", "never")}
    agg = {r["policy"]: r for r in result["aggregate"]}
    assert agg["fixed:5"]["scenarios"] == 2
    printed = capsys.readouterr().out
    assert "== aggregate over scenarios" in printed and "IQM [95% CI]" in printed


def test_tuned_heuristics_join_and_the_best_is_the_reference(capsys):
    from uwb_env.training.evaluate import DEFAULT_TUNED
    from uwb_env.training.tune import load_tuned

    tuned = load_tuned(str(DEFAULT_TUNED))
    results = main(Args(policies=["never"], seeds=3, max_cycles=30, sweep=False, workers=1, out=None,
                        progress=False))
    rows = {r["policy"]: r for r in results["summary"]}
    assert set(tuned["tuned"].values()) <= set(rows)
    assert results["reference"] == tuned["best_tuned_heuristic"] and results["reference_kind"] == "tuned"
    never = rows["never"]
    assert never["iqm_tag_error_ci_low_m"] <= never["iqm_tag_error_m"] <= never["iqm_tag_error_ci_high_m"]
    assert never["vs_reference"] == results["reference"]
    diff = never["iqm_tag_error_m"] - rows[results["reference"]]["iqm_tag_error_m"]
    assert never["iqm_diff_vs_reference_m"] == pytest.approx(diff)
    assert never["significant_vs_reference"] == (not never["iqm_diff_ci_low_m"] <= 0 <= never["iqm_diff_ci_high_m"])
    printed = capsys.readouterr().out
    assert f"reference: {results['reference']} (tuned" in printed and "catastr." in printed
    # Without a tuned file the reference is the best heuristic run, by return, and says so.
    results = main(Args(policies=["fixed:5", "never", "oracle:0.2"], seeds=2, max_cycles=30, sweep=False,
                        workers=1, out=None, progress=False, tuned="none"))
    best = max((r for r in results["summary"] if r["policy"] != "oracle:0.2"), key=lambda r: r["return"])
    assert results["reference"] == best["policy"] and "untuned" in results["reference_kind"]


def test_per_anchor_heuristics_get_their_actions_in_the_same_scenario():
    """A per-anchor heuristic is run with the per-anchor actions (re-locate me / team round) on
    the scenario everyone else runs; its anchor rounds show up in the calibration rate."""
    from uwb_env.training.evaluate import run_episode
    from uwb_env.training.tune import FAMILIES, spec_of

    from uwb_env.config import EnvConfig

    config = EnvConfig.from_dict({"max_cycles": 120}).to_dict()
    assert config["action_mode"] == "calibrate"
    per_anchor = run_episode("per_anchor_threshold:0.1", EVAL_SEED_BASE, config)
    assert per_anchor["calibrations_per_min"] > 0 and np.isfinite(per_anchor["mean_tag_error_m"])
    assert "per_anchor_threshold" in FAMILIES  # the tuner tunes it like the team heuristics
    assert spec_of("per_anchor_threshold", 0.12) == "per_anchor_threshold:0.12"


def test_summary_json_names_the_shipped_tuned_file_without_an_install_path(tmp_path):
    """summary.json is committed as the main job's result: the same on any install."""
    import json

    from uwb_env.training.evaluate import DEFAULT_TUNED, write_outputs

    results = {"summary": [{"policy": "fixed:10", "iqm_tag_error_m": 0.1}], "seeds": [1], "config": {},
               "reference": None, "reference_kind": None, "tuned_file": str(DEFAULT_TUNED.resolve()),
               "matched_budget": None, "episodes": []}
    write_outputs(results, str(tmp_path), plots=False)
    assert json.loads((tmp_path / "summary.json").read_text())["tuned_file"] == "the shipped training/tuned/default.json"

"""Does the learned per-anchor scheduler beat the best tuned heuristic? The protocol, on the suite.

For every scenario of the suite (training/scenarios/suite/suite.yml, held-out ones included):

1. tunes the deployable heuristic families (fixed interval, team uncertainty threshold, and
   the per-anchor thresholds on the predicted std and on the drift since calibration, which
   use the same per-anchor actions as the learned policy) on
   the scenario's validation seeds, for the env's return (the learned policy's objective): a
   grid, then one bisection round around each family's best;
2. runs the best tuned heuristic and the learned scheduler (one model for every scenario and
   team size; the training seed with the best validation score; a residual over the per-anchor
   rule, whose base is the per-anchor family and threshold that scored higher in step 1) on
   >= 100 test seeds;
3. reports IQM / median tag error with 95 % bootstrap CIs, the catastrophic rate, the time
   spent calibrating, and the paired IQM difference learned - heuristic with its CI.

On the default scenario it also runs the other training seeds' models (the spread across
training seeds) and a ground-truth planner, the reference from above (the headroom and the gap
closed): by default one step of policy improvement over the best tuned heuristic itself
(``rollout:60@<best heuristic>``, agents/lookahead.py), so the headroom is measured above the
heuristic the learned model must beat. Training is ``training/train_anchor_set.py`` (``--models`` names its outputs).

Writes benchmarks/results/bench_scheduling.json (``--quick``: bench_scheduling_quick.json, a
smoke run on 3 scenarios, few seeds, short episodes) and docs/results/scheduling/
(suite.csv, table.md, suite.png) unless ``--quick``.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import print_table, write_results  # noqa: E402
from benchmarks.bench_protocol import code_version  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs" / "results" / "scheduling"
# Deployable families and their grids (the per-anchor family uses the learned policy's actions).
GRIDS = {
    "fixed": (10, 20, 40, 80, 160),
    "threshold": (0.06, 0.12, 0.25, 0.5, 1.0),
    "per_anchor_threshold": (0.08, 0.15, 0.3, 0.6, 1.2),
    # the same rule on the drift since the anchor's last calibration (agents/per_anchor.py)
    "per_anchor_drift": (0.08, 0.15, 0.3, 0.6, 1.2),
}
INTEGER = {"fixed"}


def learned_base(tuned: dict) -> str:
    """The learned residual's base: of the families it can take as its base rule (the per-anchor
    ones and the team threshold) the one that scored highest on the validation seeds, at its
    tuned threshold -> the ``@`` part of its spec (``T``, ``drift:T`` or ``team:T``)."""
    from uwb_env.agents import per_anchor

    returns = tuned["validation_returns"]
    return per_anchor.learned_base(max((tuned["best_of_family"][f] for f in per_anchor.BASE_FAMILIES
                                        if f in tuned["best_of_family"]), key=returns.get))


def spec_of(family: str, value: float) -> str:
    return f"{family}:{int(round(value))}" if family in INTEGER else f"{family}:{value:.4g}"


def tune_scenario(config: dict, seeds: list[int], workers: int, label: str, known: dict | None = None,
                  families=None) -> dict:
    """Grid + one bisection round per family on validation seeds; returns the record.
    ``known``: validation returns of the families not in ``families`` (default: all of GRIDS),
    taken as they are (an earlier run's, checked by :func:`reusable`)."""
    from uwb_env.training.evaluate import run_jobs

    families = list(GRIDS) if families is None else list(families)
    scores: dict[str, float] = {s: v for s, v in (known or {}).items() if s.partition(":")[0] not in families}

    def run(specs):
        specs = [s for s in dict.fromkeys(specs) if s not in scores]
        episodes = run_jobs([(s, seed, config) for s in specs for seed in seeds], workers, label, show=False)
        for s in specs:
            scores[s] = float(np.mean([e["return"] for e in episodes if e["policy"] == s]))

    run([spec_of(f, v) for f in families for v in GRIDS[f]])
    refine = []
    for f in families:
        grid = GRIDS[f]
        values = sorted(grid)
        i = int(np.argmax([scores[spec_of(f, v)] for v in values]))
        for j in (i - 1, i + 1):
            if 0 <= j < len(values):
                mid = 0.5 * (values[i] + values[j]) if f in INTEGER else float(np.sqrt(values[i] * values[j]))
                refine.append(spec_of(f, mid))
    run(refine)
    best_of = {f: max((s for s in scores if s.startswith(f + ":")), key=scores.get) for f in GRIDS}
    best = max(best_of.values(), key=scores.get)
    return {"best": best, "best_of_family": best_of, "validation_returns": scores,
            "validation_seeds": [seeds[0], seeds[-1]]}


def reusable(row: dict | None, seeds: list[int], a, config: dict) -> dict | None:
    """``row`` (an earlier run's record of this scenario) when its heuristic side can be reused:
    same test and validation seeds, the best heuristic's first ``a.spot_check`` test episodes
    reproduce its recorded tag errors bit for bit at today's code, and the per-anchor family's
    tuned spec (the learned policy's base) reproduces its recorded validation return (else None:
    recompute). The lookahead is reused without a re-run (same dynamics, checked here).

    With ``a.retune`` (families whose policies changed, to be tuned again): the check is one
    family that did not change, its tuned spec's validation return reproduced bit for bit (the
    dynamics did not change); the best heuristic's test episodes are checked as above only when
    its family is not retuned."""
    from uwb_env.training.evaluate import run_jobs

    if row is None or row.get("test_seeds") != [seeds[0], seeds[-1]] or "tuning" not in row:
        return None
    v0, v1 = row["tuning"]["validation_seeds"]
    if v1 - v0 + 1 != a.val_seeds:
        return None
    check = seeds[: a.spot_check]
    retune = set(a.retune or ())
    best_family = row["best_heuristic"].partition(":")[0]
    kept = [f for f in GRIDS if f not in retune]
    recorded = row["tuning"]["best_of_family"]
    if not kept or any(f not in recorded for f in kept):  # a family the earlier run did not tune
        return None
    # the per-anchor rule the learned policy stands on, or (with retuned families) one kept family
    base = recorded[kept[0] if retune else "per_anchor_threshold"]
    jobs = [] if best_family in retune else [(row["best_heuristic"], s, config) for s in check]
    if base != row["best_heuristic"]:
        jobs += [(base, s, config) for s in range(v0, v1 + 1)]
    episodes = run_jobs(jobs, a.workers, "spot check", show=False)
    ok = True
    if best_family not in retune:
        again = arrays(episodes, row["best_heuristic"])[0]
        ok = again.tolist() == row["errors_m"]["heuristic"][: len(check)]
    if base != row["best_heuristic"]:
        ok &= float(np.mean([e["return"] for e in episodes if e["policy"] == base])) == \
            row["tuning"]["validation_returns"][base]
    if not ok:
        print("spot check: the earlier run does not reproduce at today's code; recomputing", flush=True)
        return None
    return row


def model_digest(path: str) -> str:
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def describe(errors: np.ndarray, calib: np.ndarray, rate: np.ndarray, returns: np.ndarray) -> dict:
    from uwb_env.evaluation.stats import bootstrap_ci, catastrophic_rate

    iqm, med, cat = bootstrap_ci(errors, "iqm"), bootstrap_ci(errors, "median"), catastrophic_rate(errors)
    return {"iqm_m": iqm.value, "iqm_ci": [iqm.ci_low, iqm.ci_high], "median_m": med.value,
            "median_ci": [med.ci_low, med.ci_high], "mean_m": float(errors.mean()),
            "catastrophic_rate": cat.value, "catastrophic_ci_high": cat.ci_high,
            "fraction_calibrating": float(calib.mean()), "calibrations_per_min": float(rate.mean()),
            "return": float(returns.mean()), "n": int(errors.size)}


def compare(learned: np.ndarray, heuristic: np.ndarray) -> dict:
    """Paired by seed: IQM(learned) - IQM(heuristic) and the relative improvement (> 0: learned better)."""
    from uwb_env.evaluation.stats import paired_difference, paired_relative_improvement, probability_of_improvement

    diff = paired_difference(learned, heuristic, "iqm")
    rel = paired_relative_improvement(learned, heuristic, "iqm")
    poi = probability_of_improvement(learned, heuristic)
    return {"iqm_difference_m": diff.value, "iqm_difference_ci": [diff.ci_low, diff.ci_high],
            "improvement": rel.value, "improvement_ci": [rel.ci_low, rel.ci_high],
            "significant": diff.excludes_zero(), "probability_of_improvement": poi.value}


def arrays(episodes: list[dict], spec: str):
    rows = sorted((e for e in episodes if e["policy"] == spec), key=lambda e: e["seed"])
    return tuple(np.array([e[k] for e in rows]) for k in
                 ("mean_tag_error_m", "fraction_calibrating", "calibrations_per_min", "return"))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--models", nargs="+", default=[str(ROOT / f"runs/anchor_set/seed{i}") for i in range(3)],
                   help="training outputs, one per training seed (training/train_anchor_set.py --out: each one's "
                   "best/ is used; training/train_distilled.py --out: its model.npz; or a shipped model's folder, e.g. "
                   "agents/models/anchor_set)")
    p.add_argument("--scenarios", nargs="*", default=None, help="default: the whole suite")
    p.add_argument("--test-seeds", type=int, default=100)
    p.add_argument("--val-seeds", type=int, default=10)
    p.add_argument("--lookahead-seeds", type=int, default=100, help="0: skip the lookahead reference")
    p.add_argument("--lookahead", default="rollout", help="the ground-truth reference's spec. 'rollout' (default): "
                   "one step of policy improvement over the default scenario's best tuned heuristic, "
                   "rollout:60@<best heuristic>; 'lookahead': the planner over the tuned fixed interval K, branches "
                   "cut at 2.5K steps (lookahead:2.5K@K); or any planner spec")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--max-cycles", type=int, default=None, help="override every scenario's episode length")
    p.add_argument("--resume", action="store_true", help="keep the scenarios an interrupted run finished "
                   "(benchmarks/results/bench_scheduling_detail.json, same model and seed count)")
    p.add_argument("--reuse-heuristics", action="store_true", help="take each scenario's heuristic tuning, "
                   "heuristic test episodes and lookahead from the detail file of an earlier run when the best "
                   "heuristic's first --spot-check test seeds reproduce it exactly (else recompute them): the "
                   "learned model changed, the dynamics did not")
    p.add_argument("--retune", nargs="+", default=None, choices=list(GRIDS),
                   help="with --reuse-heuristics: families whose policies changed; they are tuned again on the "
                   "validation seeds (and the best heuristic re-run on the test seeds if it changes), the other "
                   "families' validation returns are reused after a bit-exact check of one of them")
    p.add_argument("--spot-check", type=int, default=5, help="test seeds re-run per scenario for --reuse-heuristics "
                   "(>= 1); the lookahead options do not apply to a reused lookahead")
    a = p.parse_args()
    if a.spot_check < 1:
        p.error(f"--spot-check={a.spot_check}: must be >= 1 (reuse is only ever checked, never assumed)")
    if a.quick:
        a.test_seeds, a.val_seeds, a.lookahead_seeds, a.max_cycles = 6, 3, 2, 60
        a.scenarios = a.scenarios or ["default", "three_anchors", "eight_anchors"]

    from uwb_env.training.evaluate import run_jobs
    from uwb_env.training.suite import load_suite

    from uwb_env.evaluation.stats import gap_closed_fraction, iqm, paired_relative_improvement

    started = time.perf_counter()
    models = []
    for m in a.models:
        if (Path(m) / "summary.json").is_file():
            summary = json.loads((Path(m) / "summary.json").read_text())
            # train_anchor_set keeps its checkpoint in best/model.zip; train_distilled names its file
            path = Path(m) / summary.get("model", "best/model.zip")
        elif (Path(m) / "model.zip").is_file() and (Path(m) / "run.json").is_file():
            # a shipped checkpoint (agents/models/anchor_set): its run.json records the training
            # seed, the checkpoint's step and validation return, not the training's wall time
            run = json.loads((Path(m) / "run.json").read_text())
            summary = {"seed": run["args"]["seed"], "best_val_return": run["val_return"], "wall_s": None,
                       "steps": run["step"]}
            path = Path(m) / "model.zip"
        else:
            p.error(f"--models {m}: neither a training output (summary.json) nor a shipped model (model.zip, run.json)")
        record = path.with_name("run.json")
        run = json.loads(record.read_text()) if record.is_file() else {}
        models.append({"path": str(path), "seed": summary["seed"], "kind": run.get("env", "unknown"),
                       "margin": run.get("margin"),
                       "val_return": summary["best_val_return"], "wall_s": summary["wall_s"],
                       "steps": summary["steps"], "steps_unit": summary.get("steps_unit", "anchor decisions")})
    kinds = sorted({m["kind"] for m in models})
    if len(kinds) > 1:  # their validation scores are not on one scale (a return, a relative gain)
        p.error(f"--models: one kind of model per run, got {kinds}")
    shipped = max(models, key=lambda m: m["val_return"])  # chosen on validation seeds
    learned_model = f"learned:{shipped['path']}"
    suite = load_suite()
    names = a.scenarios or list(suite)
    name_out = "bench_scheduling_quick" if a.quick else "bench_scheduling"
    detail = ROOT / "benchmarks" / "results" / f"{name_out}_detail.json"
    per_scenario, earlier = {}, {}
    if detail.exists() and (a.resume or a.reuse_heuristics):
        earlier = json.loads(detail.read_text())
    flat_path = ROOT / "benchmarks" / "results" / f"{name_out}.json"
    earlier_version = (json.loads(flat_path.read_text()).get("code_version", "unknown") if flat_path.exists()
                       else "unknown")
    digest = model_digest(shipped["path"])  # the same path may hold a retrained model
    if shipped["margin"] is not None or shipped["kind"] == "distilled":  # its margin is part of the policy
        digest += f"+margin={shipped['margin']}"
    if a.resume:  # scenarios finished by an interrupted run with the same settings
        per_scenario = {n: r for n, r in earlier.items() if n in names
                        and r.get("learned_spec", "").rpartition("@")[0] == learned_model
                        and r.get("learned_model_sha256") == digest
                        and r["test_seeds"][1] - r["test_seeds"][0] + 1 == a.test_seeds}
    for name in names:
        if name in per_scenario:
            continue
        sc = suite[name]
        config = {**sc["config"], "max_cycles": a.max_cycles or sc["max_cycles"]}
        v0, t0 = sc["seeds"]["validation"][0], sc["seeds"]["test"][0]
        seeds = list(range(t0, t0 + a.test_seeds))
        reused = reusable(earlier.get(name), seeds, a, config) if a.reuse_heuristics else None
        partial = None  # the families whose tuning was reused while others were tuned again
        if reused is not None and a.retune:
            partial = {"families_reused": [f for f in GRIDS if f not in a.retune], "families_retuned": a.retune,
                       "from_code_version": (reused.get("heuristic_reused", {}).get("from_code_version")
                                             or reused.get("code_version") or earlier_version)}
            tuned = tune_scenario(config, list(range(v0, v0 + a.val_seeds)), a.workers, f"retune {name}",
                                  known=reused["tuning"]["validation_returns"], families=a.retune)
            best = tuned["best"]
            # test episodes are new when the best changed, or when its family's policy did (the
            # same spec string under a changed rule)
            if best != reused["best_heuristic"] or best.partition(":")[0] in a.retune:
                reused = {**reused, "stale_heuristic": True}
        elif reused is not None:
            tuned, best = reused["tuning"], reused["best_heuristic"]
        else:
            tuned = tune_scenario(config, list(range(v0, v0 + a.val_seeds)), a.workers, f"tune {name}")
            best = tuned["best"]
        if reused is not None and reused.get("stale_heuristic"):
            reused = None
        # the learned scheduler is a residual over a per-anchor rule: its base is the per-anchor
        # family and threshold that scored higher on the scenario's validation seeds
        base = learned_base(tuned)
        learned = f"{learned_model}@{base}"
        specs = [learned] if reused is not None else [best, learned]
        if name == "default":
            specs += [f"learned:{m['path']}@{base}" for m in models if m is not shipped]
        episodes = run_jobs([(s, seed, config) for s in specs for seed in seeds], a.workers, f"test {name}", show=False)
        lr = arrays(episodes, learned)
        if reused is not None:
            h_errors, h_desc = np.array(reused["errors_m"]["heuristic"]), reused["heuristic"]
        else:
            h = arrays(episodes, best)
            h_errors, h_desc = h[0], describe(*h)
        row = {"held_out": sc["held_out"], "best_heuristic": best, "learned_spec": learned, "tuning": tuned,
               "heuristic": h_desc, "learned": describe(*lr), "comparison": compare(lr[0], h_errors),
               "test_seeds": [seeds[0], seeds[-1]]}
        if reused is not None:
            origin = (reused.get("heuristic_reused", {}).get("from_code_version") or reused.get("code_version")
                      or earlier_version)
            row["heuristic_reused"] = {"from_code_version": origin,
                                       "spot_check_seeds": a.spot_check, "spot_check_identical": True}
        if partial is not None:
            row["tuning_reused"] = partial
        row["code_version"] = code_version()
        row["learned_model_sha256"] = digest
        row["errors_m"] = {"heuristic": h_errors.tolist(), "learned": lr[0].tolist()}  # by test seed, for pairing
        if (reused is not None and name == "default" and "lookahead" in reused
                and reused["lookahead"]["spec"] == lookahead_spec(a.lookahead, row)):
            row["lookahead"] = reused["lookahead"]  # recomputed against the new learned errors below
        if name == "default":
            row["learned_per_training_seed"] = {}
            for m in models:
                arr = arrays(episodes, f"learned:{m['path']}@{base}")
                row["learned_per_training_seed"][m["seed"]] = {**describe(*arr), **compare(arr[0], h_errors)}
        per_scenario[name] = row
        # a kill keeps what is done, and the earlier rows not redone yet (the reuse cache)
        pending = {n: r for n, r in earlier.items() if n not in per_scenario} if a.reuse_heuristics else {}
        detail.write_text(json.dumps({**pending, **per_scenario}, indent=1, default=float))
        c = row["comparison"]
        print(f"{name:16s} best {best:28s} heur {row['heuristic']['iqm_m']:.4f}  learned {row['learned']['iqm_m']:.4f}"
              f"  improvement {100 * c['improvement']:+.1f} % [{100 * c['improvement_ci'][0]:+.1f}, "
              f"{100 * c['improvement_ci'][1]:+.1f}]", flush=True)

    # The reference from above, last (it costs about as much as everything else together).
    default = per_scenario.get("default")
    if default is not None and "lookahead" in default and (
            default["lookahead"].get("planner") != planner_identity(lookahead_spec(a.lookahead, default))):
        del default["lookahead"]  # stored by another planner (spec, parameters or revision): recomputed
    if default is not None and "lookahead" in default:  # reused: the learned side is the new model's
        la = default["lookahead"]
        n = la["n_seeds"]
        learn_n = float(iqm(np.array(default["errors_m"]["learned"])[:n]))
        la["learned_iqm_m_same_seeds"] = learn_n
        la["gap_closed_fraction"] = (gap_closed_fraction(la["heuristic_iqm_m_same_seeds"], learn_n, la["iqm_m"])
                                     if la["headroom_ci"][0] > 0 else float("nan"))
    if default is not None and a.lookahead_seeds and "lookahead" not in default:
        sc = suite["default"]
        config = {**sc["config"], "max_cycles": a.max_cycles or sc["max_cycles"]}
        spec = lookahead_spec(a.lookahead, default)
        t0 = sc["seeds"]["test"][0]
        la_seeds = list(range(t0, t0 + min(a.lookahead_seeds, a.test_seeds)))
        la = run_jobs([(spec, s, config) for s in la_seeds], a.workers, "lookahead", show=False)
        la_err = arrays(la, spec)
        n = len(la_seeds)  # the lookahead's seeds (the first n test seeds): every figure below is on these
        h_n, l_n = (np.array(default["errors_m"][k_])[:n] for k_ in ("heuristic", "learned"))
        ref, heur_n, learn_n = float(iqm(la_err[0])), float(iqm(h_n)), float(iqm(l_n))
        headroom = paired_relative_improvement(la_err[0], h_n, "iqm")
        # a gap the lookahead does not significantly open cannot be "closed" by a fraction
        gap = gap_closed_fraction(heur_n, learn_n, ref) if headroom.ci_low > 0 else float("nan")
        default["lookahead"] = {"spec": spec, "planner": planner_identity(spec), **describe(*la_err), "n_seeds": n,
                                "errors_m": la_err[0].tolist(),
                                "heuristic_iqm_m_same_seeds": heur_n, "learned_iqm_m_same_seeds": learn_n,
                                "headroom": headroom.value, "headroom_ci": [headroom.ci_low, headroom.ci_high],
                                "gap_closed_fraction": gap}
        detail.write_text(json.dumps(per_scenario, indent=1, default=float))
        print(f"lookahead {spec}: IQM {ref:.4f} vs heuristic {heur_n:.4f} (headroom {100 * headroom.value:+.1f} %), "
              f"learned {learn_n:.4f}: gap closed {gap:.2f}", flush=True)

    improvements = {n: r["comparison"]["improvement"] for n, r in per_scenario.items()}
    worst = min(improvements, key=improvements.get)
    worse_beyond_ci = [n for n, r in per_scenario.items() if r["comparison"]["improvement_ci"][1] < 0]
    flat = {
        "code_version": code_version(), "scenarios": ", ".join(names),
        "held_out_scenarios": ", ".join(n for n in names if per_scenario[n]["held_out"]),
        "test_seeds_per_scenario": a.test_seeds, "validation_seeds_per_candidate": a.val_seeds,
        "shipped_model": str(Path(shipped["path"]).relative_to(ROOT)) if Path(shipped["path"]).is_relative_to(ROOT)
        else shipped["path"], "shipped_training_seed": shipped["seed"],
        "learned_kind": shipped["kind"],
        **{f"departure_margin_seed_{m['seed']}": m["margin"] for m in models if m["kind"] == "distilled"},
        "n_training_seeds": len(models),
        # None when a seed's wall clock is unknown (its data collected by an earlier, untimed run)
        "training_wall_s_per_seed": (None if any(m["wall_s"] is None for m in models)
                                     else max(m["wall_s"] for m in models)),
        **{f"training_wall_s_seed_{m['seed']}": m["wall_s"] for m in models},
        **{f"training_steps_seed_{m['seed']}": m["steps"] for m in models},
        "training_steps_unit": shipped["steps_unit"],
        "worst_scenario": worst, "worst_scenario_improvement": improvements[worst],
        "scenarios_worse_than_best_heuristic_beyond_ci": ", ".join(worse_beyond_ci) or "none",
        "n_scenarios_worse_beyond_ci": len(worse_beyond_ci),
        "n_scenarios_better_beyond_ci": sum(r["comparison"]["improvement_ci"][0] > 0 for r in per_scenario.values()),
        "team_sizes_run": ", ".join(str(n) for n in sorted({int(suite[n]["config"].get("sim", {}).get("n_anchors", 4))
                                                           for n in names})),
        "wall_s": time.perf_counter() - started,
        "heuristic_side_reused_scenarios": ", ".join(n for n, r in per_scenario.items() if "heuristic_reused" in r)
        or "none",
        "heuristic_side_reused_from": ", ".join(sorted({r["heuristic_reused"]["from_code_version"]
                                                        for r in per_scenario.values() if "heuristic_reused" in r}))
        or "none",
    }
    if default:
        c = default["comparison"]
        flat.update({
            "best_heuristic_default": default["best_heuristic"],
            "learned_iqm_m_default": default["learned"]["iqm_m"],
            "heuristic_iqm_m_default": default["heuristic"]["iqm_m"],
            "learned_vs_best_heuristic_iqm_improvement": c["improvement"],
            "learned_vs_best_heuristic_iqm_improvement_ci_low": c["improvement_ci"][0],
            "learned_vs_best_heuristic_iqm_improvement_ci_high": c["improvement_ci"][1],
            "learned_vs_best_heuristic_significant": c["significant"],
            "learned_fraction_calibrating_default": default["learned"]["fraction_calibrating"],
            "heuristic_fraction_calibrating_default": default["heuristic"]["fraction_calibrating"],
            **{f"improvement_training_seed_{k}": v["improvement"]
               for k, v in default["learned_per_training_seed"].items()},
        })
        if "lookahead" in default:
            la = default["lookahead"]
            flat.update({"lookahead_spec": la["spec"], "lookahead_seeds": la["n_seeds"],
                         "lookahead_headroom": la["headroom"], "lookahead_headroom_ci_low": la["headroom_ci"][0],
                         "lookahead_headroom_ci_high": la["headroom_ci"][1],
                         # null (not NaN: strict JSON) when the lookahead opens no significant gap
                         "gap_closed_fraction": la["gap_closed_fraction"] if np.isfinite(la["gap_closed_fraction"])
                         else None, "lookahead_iqm_m_default": la["iqm_m"],
                         "heuristic_iqm_m_lookahead_seeds": la["heuristic_iqm_m_same_seeds"],
                         "learned_iqm_m_lookahead_seeds": la["learned_iqm_m_same_seeds"]})
    rows = [{"scenario": n, "held_out": r["held_out"], "best heuristic": r["best_heuristic"],
             "heuristic IQM": f"{r['heuristic']['iqm_m']:.4f}", "learned IQM": f"{r['learned']['iqm_m']:.4f}",
             "improvement %": f"{100 * r['comparison']['improvement']:+.1f}",
             "CI %": "[{:+.1f}, {:+.1f}]".format(*(100 * x for x in r["comparison"]["improvement_ci"])),
             "cal. time h/l": "{:.3f}/{:.3f}".format(r["heuristic"]["fraction_calibrating"],
                                                     r["learned"]["fraction_calibrating"]),
             "catastrophic h/l": f"{r['heuristic']['catastrophic_rate']:.2f}/{r['learned']['catastrophic_rate']:.2f}"}
            for n, r in per_scenario.items()]
    print_table("learned (shipped) vs the best tuned heuristic, per scenario (IQM tag error, m)", list(rows[0]),
                [list(r.values()) for r in rows])
    write_results(name_out, flat, a.quick)
    detail.write_text(json.dumps(per_scenario, indent=1, default=float))
    if not a.quick:
        DOCS.mkdir(parents=True, exist_ok=True)
        with open(DOCS / "suite.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        lines = ["| " + " | ".join(rows[0]) + " |", "|" + " --- |" * len(rows[0])]
        lines += ["| " + " | ".join(str(v) for v in r.values()) + " |" for r in rows]
        (DOCS / "table.md").write_text("\n".join(lines) + "\n")
        plot_suite(per_scenario, DOCS / "suite.png")


def lookahead_spec(option: str, default_row: dict) -> str:
    """The ground-truth reference's spec from ``--lookahead`` and the default scenario's row."""
    if option == "rollout":  # policy improvement over the heuristic the learned model must beat
        return f"rollout:60@{default_row['best_heuristic']}"
    if option == "lookahead":  # the planner over the tuned fixed interval
        k = int(default_row["tuning"]["best_of_family"]["fixed"].partition(":")[2])
        return f"lookahead:{min(max(int(2.5 * k), 60), 300)}@{k}"
    return option


def planner_identity(spec: str) -> dict:
    """What identifies a reference planner's answers: its parameters and revision where it says
    them (``RolloutPolicy.describe``), else its spec."""
    from uwb_env.agents.registry import make_policy

    policy = make_policy(spec)
    return policy.describe() if hasattr(policy, "describe") else {"spec": spec}


def plot_suite(per_scenario: dict, path: Path) -> None:
    """IQM tag error with 95 % CIs per scenario: best tuned heuristic vs learned."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(per_scenario)
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(6, 0.9 * len(names)), 4))
    for shift, key, label in ((-0.18, "heuristic", "best tuned heuristic"), (0.18, "learned", "learned (shipped)")):
        v = np.array([per_scenario[n][key]["iqm_m"] for n in names])
        lo, hi = (np.array([per_scenario[n][key]["iqm_ci"][i] for n in names]) for i in (0, 1))
        ax.errorbar(x + shift, v, yerr=[v - lo, hi - v], fmt="o", capsize=3, label=label)
    ax.set_xticks(x, [n + (" *" if per_scenario[n]["held_out"] else "") for n in names], rotation=30, ha="right")
    ax.set_ylabel("IQM of episode mean tag error (m)")
    ax.set_title("test seeds, 95 % bootstrap CIs (* held out of training)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()

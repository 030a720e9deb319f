"""Distil the ground-truth rollout reference into a deployable scheduler (agents/distilled.py).

Usage::

    python -m uwb_env.training.train_distilled --seed 0 --out runs/distilled/seed0

1. **Collect** (training seeds only): the rollout reference ``rollout:H@<base>`` (the
   scenario's tuned per-anchor rule, ``training/tuned/suite_learned_base.json``) runs
   ``episodes`` episodes of ``scenario`` on training seeds ``1000 + seed * episodes`` onwards
   (disjoint between training seeds). At each of its decisions it records what a deployment
   sees (the anchors' observations and the rule's action) and the gain of each departure (a team
   round now; holding off until the next decision) over the rule, measured on the *true* state:
   the mean over its sampled futures of the paired difference in summed reward. Each episode is
   saved as it finishes (``out/data``); running the command again resumes.
2. **Fit** a :class:`~uwb_env.agents.distilled.GainModel` (an MLP, torch, hyperparameters in
   ``training/hyperparams/distilled.yml``) by least squares to those gains: it predicts the
   expected gain of a departure given what is observable, and departing where it is positive
   is the decision a deployment can make. Early stopping on a fifth of the episodes.
3. **Choose the margin** (depart when a predicted gain exceeds it) on validation seeds of the
   validation scenarios, each with its own tuned base: the margin with the highest mean return
   gain over the rule, relative to the rule's return per scenario; "never depart" (the rule
   itself, gain 0) is a candidate, so the choice does not lose to the rule on validation.

Writes ``out/model.npz`` (+ ``model.json``), ``out/run.json`` (the margin, the validation table)
and ``out/summary.json`` (seed, wall time, data size, best validation score), the files
``benchmarks/bench_scheduling.py --models`` reads.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from uwb_env.agents.distilled import (
    TEAM_FEATURES,
    DistilledPolicy,
    GainModel,
    base_spec,
    parse_base,
    team_features,
)
from uwb_env.training.hyperparams_io import load_block

HERE = Path(__file__).resolve().parent
ENV_ID = "uwb_env/Distilled"
DEFAULT_HYPERPARAMS = HERE / "hyperparams" / "distilled.yml"
LEARNED_BASES = HERE / "tuned" / "suite_learned_base.json"
EPISODE_SEED_BASE = 1000  # collection episodes: 1000 + seed * episodes ... (the suite's training range)
VALIDATION_SEED_BASE = 500_000
VALIDATION_SCENARIOS = ("default", "harsh_radio", "fast_robots", "low_drift", "five_anchors", "eight_anchors")
MARGINS = (0.6, 0.4, 0.3, 0.2, 0.15, 0.1, 0.05, 0.0)


@dataclass
class Args:
    seed: int = 0
    out: str = "runs/distilled/seed0"
    scenario: str = "default"
    """the scenario the rollout reference is run on (its tuned base is the rule distilled over)"""
    episodes: int = 100
    """rollout episodes collected (training seeds 1000 + seed * episodes onwards: disjoint between
    training seeds run with the same value)"""
    workers: int = 2
    horizon_steps: int = 60
    n_futures: int = 8
    decide_every_steps: int = 10
    val_seeds: int = 30
    """validation seeds per validation scenario for the margin"""
    val_scenarios: tuple[str, ...] = VALIDATION_SCENARIOS
    hyperparams: str = str(DEFAULT_HYPERPARAMS)
    hp: list[str] = dataclasses.field(default_factory=list)
    max_cycles: int | None = None
    """shorter episodes everywhere (tests); None: the scenarios' own"""


def learned_bases(path: str | Path = LEARNED_BASES) -> dict[str, str]:
    """Scenario -> the tuned base rule of the residual schedulers (``drift:0.21``, ``0.3``, ``team:1``)."""
    return json.loads(Path(path).read_text())["base"]


def _scenario_config(name: str, max_cycles: int | None):
    from uwb_env.training.suite import load_suite

    from uwb_env.config import EnvConfig

    sc = load_suite()[name]
    # the scenario's own action mode: the harness switches it to the policy's (a per-anchor rule
    # and the distilled policy: per_anchor; the team threshold rule: team requests)
    return EnvConfig.from_dict({**sc["config"], "max_cycles": max_cycles or sc["max_cycles"]})


def collect_episode(job: tuple) -> dict:
    """One rollout episode (``job`` = seed, scenario, base, horizon, futures, decide, max_cycles):
    per decision, the observed per-anchor fields, the rule's actions and each move's summed
    reward in each future."""
    from uwb_env.agents.lookahead import RolloutPolicy
    from uwb_env.agents.per_anchor import TEAM_ROUND
    from uwb_env.training.evaluate import run_policy_episode

    from uwb_env.system import OBS_FIELDS

    seed, scenario, base, horizon, futures, decide, max_cycles = job
    config = _scenario_config(scenario, max_cycles)
    rows = []

    class Recording(RolloutPolicy):
        def act(self, observations, infos):
            self._seen = observations
            return super().act(observations, infos)

        def _decide(self, moves):
            best = super()._decide(moves)
            agents = list(self._seen)
            nan = np.full(self.n_futures, np.nan)
            base = np.array([moves["base"][a] for a in agents])
            if self.action_mode != "per_anchor":  # the team threshold rule's request (1) is a team round
                base = np.where(base == 1, TEAM_ROUND, base)
            rows.append((np.stack([self._seen[a][-len(OBS_FIELDS):] for a in agents]), base, self.last_totals["base"],
                         self.last_totals.get("team", nan), self.last_totals.get("wait", nan), best, self.t))
            return best

    policy = Recording(base_spec(base), horizon_steps=horizon, n_futures=futures, decide_every_steps=decide,
                       dt_s=config.sim.dt_s)
    started = time.process_time()
    episode = run_policy_episode(policy, seed, config)
    return {"seed": seed, "rows": rows, "cpu_s": time.process_time() - started,
            "mean_tag_error_m": episode["mean_tag_error_m"], "max_cycles": config.max_cycles, "dt_s": config.sim.dt_s}


def _save_episode(path: Path, ep: dict) -> None:
    rows = ep["rows"]
    np.savez(path, own=np.stack([r[0] for r in rows]), base=np.stack([r[1] for r in rows]),
             totals_base=np.stack([r[2] for r in rows]), totals_team=np.stack([r[3] for r in rows]),
             totals_wait=np.stack([r[4] for r in rows]), chosen=np.array([r[5] for r in rows]),
             t=np.array([r[6] for r in rows]), cpu_s=ep["cpu_s"], max_cycles=ep["max_cycles"], dt_s=ep["dt_s"])


def collect(args: Args, base: str, out: Path) -> list[Path]:
    data = out / "data"
    data.mkdir(parents=True, exist_ok=True)
    # what the stored episodes were collected with: a resume with other settings is refused
    from uwb_env.agents.lookahead import RolloutPolicy

    manifest = {"scenario": args.scenario, "base": base, "horizon_steps": args.horizon_steps,
                "n_futures": args.n_futures, "decide_every_steps": args.decide_every_steps,
                "max_cycles": args.max_cycles, "rollout_revision": RolloutPolicy.REVISION}
    stored = data / "manifest.json"
    if stored.exists():
        earlier = json.loads(stored.read_text())
        settings = {k: v for k, v in earlier.items() if not k.startswith("collect_")}
        if settings != manifest:
            raise ValueError(f"{stored}: collected with {settings}, not {manifest}: use another --out")
        manifest.update({k: v for k, v in earlier.items() if k.startswith("collect_")})
    else:  # episodes already there without a manifest: their collection time is unknown
        manifest["collect_wall_s"] = None if any(data.glob("ep*.npz")) else 0.0
    stored.write_text(json.dumps(manifest, indent=1))
    first = EPISODE_SEED_BASE + args.seed * args.episodes
    seeds = list(range(first, first + args.episodes))
    todo = [s for s in seeds if not (data / f"ep{s}.npz").exists()]
    jobs = [(s, args.scenario, base, args.horizon_steps, args.n_futures, args.decide_every_steps, args.max_cycles)
            for s in todo]
    started = time.perf_counter()
    if jobs:
        if args.workers == 1:
            results = map(collect_episode, jobs)
            for ep in results:
                if ep["rows"]:
                    _save_episode(data / f"ep{ep['seed']}.npz", ep)
        else:
            context = multiprocessing.get_context("forkserver")
            with ProcessPoolExecutor(max_workers=args.workers, mp_context=context) as pool:
                for ep in pool.map(collect_episode, jobs):  # saved as each finishes: a kill loses one
                    if ep["rows"]:
                        _save_episode(data / f"ep{ep['seed']}.npz", ep)
        if manifest["collect_wall_s"] is not None:  # the wall clock of every collection session
            manifest["collect_wall_s"] += time.perf_counter() - started
            stored.write_text(json.dumps(manifest, indent=1))
    return [data / f"ep{s}.npz" for s in seeds if (data / f"ep{s}.npz").exists()]


def _gains(totals: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Mean over futures of a move's summed reward minus the rule's, per decision; a move the
    rollout did not simulate (NaN in every future) was the rule's own branch: 0. Anything else
    non-finite is an error, not a zero."""
    diff = np.asarray(totals, dtype=np.float64) - base
    skipped = np.isnan(totals).all(-1)
    if not np.isfinite(diff[~skipped]).all():
        raise ValueError("rollout totals: non-finite reward in a simulated move")
    return np.where(skipped, 0.0, np.nan_to_num(diff).mean(-1))


def gain_table(files: list[Path], threshold_m: float, horizon_steps: int):
    """(features, gains (team, wait), episode index) over every recorded decision. A move the
    rollout did not simulate was the rule's own in every future: gain 0."""
    X, Y, E = [], [], []
    for i, f in enumerate(files):
        with np.load(f) as z:
            dt, max_cycles = float(z["dt_s"]), int(z["max_cycles"])
            for j in range(len(z["t"])):
                X.append(team_features(z["own"][j], z["base"][j], threshold_m, dt, max_cycles - int(z["t"][j]),
                                       horizon_steps))
                base = z["totals_base"][j]
                Y.append([_gains(z["totals_team"][j], base), _gains(z["totals_wait"][j], base)])
                E.append(i)
    return np.array(X), np.array(Y), np.array(E)


def rollout_gains(files: list[Path]) -> dict:
    """The rollout reference's own departures in the collected episodes: how often, and their
    measured gain per episode (on the futures that chose them: biased upwards), beside the mean
    gain of each departure over all decisions (with its standard error)."""
    chosen, taken, every = [], [], {m: [] for m in ("team", "wait")}
    for f in files:
        with np.load(f) as z:
            base = z["totals_base"]
            gains = {m: _gains(z[f"totals_{m}"], base) for m in ("team", "wait")}
            pick = z["chosen"]
            chosen.append(pick)
            taken.append(sum(np.where(pick == m, gains[m], 0.0).sum() for m in gains))
            for m in gains:
                every[m].append(gains[m])
    pick = np.concatenate(chosen)
    out = {"episodes": len(files), "decisions": int(len(pick)),
           "departure_rate": {m: float((pick == m).mean()) for m in ("team", "wait")},
           "gain_per_episode_of_its_departures": float(np.mean(taken))}
    for m, g in every.items():
        g = np.concatenate(g)
        out[f"mean_gain_{m}"] = float(g.mean())
        out[f"mean_gain_{m}_se"] = float(g.std(ddof=1) / np.sqrt(len(g)))
    return out


def fit_gain_model(X: np.ndarray, Y: np.ndarray, episodes: np.ndarray, hp: dict, seed: int, horizon_steps: int,
                   decide_every_steps: int):
    """Least-squares MLP with early stopping on a fifth of the episodes -> (GainModel, record)."""
    import torch

    ids = np.unique(episodes)
    if len(ids) < 2:
        raise ValueError(f"episodes: {len(ids)} with decisions; the fit needs at least 2 (one held out)")
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    held = rng.choice(ids, size=max(1, len(ids) // 5), replace=False)
    val = np.isin(episodes, held)
    mean, scale = X[~val].mean(0), X[~val].std(0)
    constant = ~(scale > 1e-9)  # e.g. one team size, one step length in the data
    scale = np.where(constant, 1.0, scale)
    Xs = torch.tensor((X - mean) / scale, dtype=torch.float32)
    Yt = torch.tensor(Y, dtype=torch.float32)
    hidden = [int(h) for h in hp["hidden"]]
    layers, width = [], X.shape[1]
    for h in hidden:
        layers += [torch.nn.Linear(width, h), torch.nn.Tanh()]
        width = h
    layers.append(torch.nn.Linear(width, Y.shape[1]))
    net = torch.nn.Sequential(*layers)
    opt = torch.optim.Adam(net.parameters(), lr=float(hp["learning_rate"]), weight_decay=float(hp["weight_decay"]))
    tr_idx = np.flatnonzero(~val)
    best, best_state, since, history = np.inf, None, 0, []
    batch = int(hp["batch_size"])
    for epoch in range(int(hp["max_epochs"])):
        net.train()
        for chunk in np.array_split(rng.permutation(tr_idx), max(1, len(tr_idx) // batch)):
            opt.zero_grad()
            loss = torch.nn.functional.mse_loss(net(Xs[chunk]), Yt[chunk])
            loss.backward()
            opt.step()
        net.eval()
        with torch.no_grad():
            v = float(torch.nn.functional.mse_loss(net(Xs[val]), Yt[val]))
        history.append(v)
        if v < best - 1e-9:
            best, best_state, since = v, [p.detach().clone() for p in net.parameters()], 0
        else:
            since += 1
            if since >= int(hp["patience"]):
                break
    if best_state is None:
        raise RuntimeError("gain model: the held-out loss was never finite (non-finite features or gains?)")
    with torch.no_grad():
        for p, q in zip(net.parameters(), best_state, strict=True):
            p.copy_(q)
        # a feature constant in the data got no gradient: its weights are still random, and on a
        # team size or step length the data never had they would move every prediction. It is
        # information the data cannot use: cut it.
        net[0].weight[:, torch.from_numpy(constant)] = 0.0
    linears = [m for m in net if isinstance(m, torch.nn.Linear)]
    weights = tuple((m.weight.detach().numpy().astype(np.float64).T, m.bias.detach().numpy().astype(np.float64))
                    for m in linears)
    model = GainModel(mean, scale, weights, horizon_steps, decide_every_steps)
    baseline = float(((Y[val] - Y[~val].mean(0)) ** 2).mean())  # predicting the mean gain
    # What the model's departures would gain on the held-out episodes, by margin: the rollout's
    # measured gain of the move it picks, summed per episode (first order: one decision at a time)
    pred = model.evaluate(X[val])
    rule_team = X[val][:, TEAM_FEATURES.index("base_share_team")] == 1.0
    pred[rule_team, 0] = -np.inf  # as the policy: no "team" departure when the rule asks for one
    move = pred.argmax(1)
    measured = Y[val][np.arange(len(move)), move]
    n_held = len(held)
    offline = {f"{m:g}": {"departure_rate": float((pred.max(1) > m).mean()),
                          "gain_per_episode": float(measured[pred.max(1) > m].sum() / n_held)} for m in MARGINS}
    return model, {"held_out_mse": best, "held_out_mse_of_mean": baseline, "epochs": len(history),
                   "decisions": int(len(X)), "held_out_decisions": int(val.sum()), "held_out_episodes": n_held,
                   "held_out_offline": offline}


def _validation_episode(job: tuple) -> tuple:
    from uwb_env.training.evaluate import run_policy_episode

    model_path, margin, base, scenario, seed, max_cycles = job
    measure, threshold = parse_base(base)
    config = _scenario_config(scenario, max_cycles)
    if margin is None:  # the rule itself
        from uwb_env.agents.registry import make_policy

        policy = make_policy(base_spec(base), config.sim.dt_s)
    else:
        policy = DistilledPolicy(GainModel.load(model_path), margin, threshold, measure)
    ep = run_policy_episode(policy, seed, config)
    return scenario, margin, seed, float(ep["return"])


def choose_margin(args: Args, model_path: Path, bases: dict) -> dict:
    """Validation returns per candidate margin; the best by mean relative return gain over the rule."""
    jobs = [(str(model_path), m, bases[sc], sc, VALIDATION_SEED_BASE + k, args.max_cycles)
            for sc in args.val_scenarios for m in (None, *MARGINS) for k in range(args.val_seeds)]
    context = multiprocessing.get_context("forkserver")
    if args.workers == 1:
        results = list(map(_validation_episode, jobs))
    else:
        with ProcessPoolExecutor(max_workers=args.workers, mp_context=context) as pool:
            results = list(pool.map(_validation_episode, jobs, chunksize=8))
    returns: dict = {}
    for sc, m, _, r in results:
        returns.setdefault(sc, {}).setdefault("rule" if m is None else f"{m:g}", []).append(r)
    table = {}
    for key in ["rule"] + [f"{m:g}" for m in MARGINS]:
        table[key] = float(np.mean([(np.mean(returns[sc][key]) - np.mean(returns[sc]["rule"]))
                                    / abs(np.mean(returns[sc]["rule"])) for sc in returns]))
    best = max(table, key=table.get)
    return {"margin": None if best == "rule" else float(best), "relative_gain": table,
            "per_scenario_mean_return": {sc: {k: float(np.mean(v)) for k, v in d.items()} for sc, d in returns.items()}}


def main(args: Args) -> dict:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    started = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    hp = load_block(args.hyperparams, ENV_ID, args.hp)
    bases = learned_bases()
    unknown = sorted({args.scenario, *args.val_scenarios} - set(bases))
    if unknown:
        raise ValueError(f"scenarios {unknown}: no tuned base in {LEARNED_BASES.name}")
    base = bases[args.scenario]
    files = collect(args, base, out)
    collected_s = time.perf_counter() - started
    collect_wall = json.loads((out / "data" / "manifest.json").read_text())["collect_wall_s"]
    if not files:
        raise RuntimeError("no rollout decisions were recorded (episodes too short for a decision?)")
    cpu = [float(np.load(f)["cpu_s"]) for f in files]
    cpu_s = float(sum(cpu)) if np.isfinite(cpu).all() else None  # None: episodes of an older collector
    X, Y, E = gain_table(files, parse_base(base)[1], args.horizon_steps)
    reference = rollout_gains(files)
    model, fit = fit_gain_model(X, Y, E, hp, args.seed, args.horizon_steps, args.decide_every_steps)
    model_path = out / "model.npz"
    model.save(model_path)
    chosen = choose_margin(args, model_path, bases)
    margin = chosen["margin"]
    wall = time.perf_counter() - started
    run = {"env": "distilled", "seed": args.seed, "scenario": args.scenario, "base": base,
           "margin": margin, "fit": fit, "rollout": reference, "validation": chosen,
           "hyperparams": hp, "args": dataclasses.asdict(args)}
    (out / "run.json").write_text(json.dumps(run, indent=1))
    # the training seed's wall clock: every collection session (the data may come from earlier
    # runs) plus this run's fit and validation; None when a session's time is unknown
    fit_wall = wall - collected_s
    summary = {"seed": args.seed, "model": "model.npz",
               "wall_s": None if collect_wall is None else collect_wall + fit_wall, "collect_wall_s": collect_wall,
               "fit_and_validation_wall_s": fit_wall, "this_run_wall_s": wall, "collect_cpu_s": cpu_s,
               "episodes": len(files), "steps": int(len(X)), "steps_unit": "rollout decisions",
               "best_val_return": chosen["relative_gain"]["rule" if margin is None else f"{margin:g}"]}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps({**summary, "margin": margin, "fit": fit}, indent=1))
    return summary


def parse_args(argv=None) -> Args:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    d = Args()
    for f in dataclasses.fields(Args):
        flag = "--" + f.name.replace("_", "-")
        if f.name == "hp":
            p.add_argument(flag, nargs="*", default=[], help="hyperparameter overrides key=value")
        elif f.name == "val_scenarios":
            p.add_argument(flag, nargs="+", default=list(d.val_scenarios))
        elif f.name == "max_cycles":
            p.add_argument(flag, type=int, default=None)
        else:
            p.add_argument(flag, type=type(getattr(d, f.name)), default=getattr(d, f.name))
    ns = p.parse_args(argv)
    return Args(**{**vars(ns), "val_scenarios": tuple(ns.val_scenarios)})


if __name__ == "__main__":
    main(parse_args())

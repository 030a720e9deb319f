"""GROUND TRUTH reference schedulers: a lookahead planner on copies of the true system state.

:class:`LookaheadPolicy` is a rollout (policy-improvement) planner over a base heuristic, the
fixed interval counted from the last calibration (give it the tuned interval and a horizon
about as long). At a decision point it deep-copies the env
(true robot positions, odometry, running round: everything), gives each copy a generator seeded
from the planner's *own* generator, and simulates "calibrate now" and "wait" (no request until
the next decision point), each followed by the base heuristic, over ``n_futures`` sampled
futures. Both candidates of one future share the seed (common random numbers).

Each branch runs to the end of its first full calibration cycle (until the base heuristic would
start the branch's second round; at most ``horizon_steps`` steps), and the branches are compared
by their reward *per step* (the renewal-reward criterion of an average-cost problem): comparing
totals over one fixed horizon would favour calibrating early, whose benefit lies inside the
horizon while the later calibration's is cut off. The real env's generator is never copied,
read or advanced: the copy is made with the real generator pre-mapped to the fresh one.

:class:`ClairvoyantPolicy` is the same planner with one future, *the real one*: its copies carry
the real generator's state, so it knows the noise to come. An optimistic bound, not a plan.

Both read ground truth (``uses_ground_truth = True``) and need the env: the evaluation harness
calls :meth:`bind` before each episode.
"""

from __future__ import annotations

import copy

import numpy as np


class LookaheadPolicy:
    """See the module docstring.

    Args:
        horizon_steps: at most this many simulated steps per candidate (a cycle is cut there).
        n_futures: sampled futures (each simulated once per candidate).
        base_interval_steps: the base heuristic calibrates when this many steps have passed since
            the last calibration; it acts between decisions and in the simulated continuations.
        decide_every_steps: plan this often (default horizon / 15, at least 4); between decision
            points it does not request. "Wait" means: no request until the next decision point.
    """

    uses_ground_truth = True
    clairvoyant = False

    def __init__(self, horizon_steps: int = 30, n_futures: int = 8, base_interval_steps: int = 10,
                 decide_every_steps: int | None = None):
        if decide_every_steps is None:  # the cost per episode stays ~ 2 * 15 * n_futures * episode length
            decide_every_steps = max(4, horizon_steps // 15)
        for name, value in (("horizon_steps", horizon_steps), ("n_futures", n_futures),
                            ("base_interval_steps", base_interval_steps), ("decide_every_steps", decide_every_steps)):
            if int(value) != value or value < 1:
                raise ValueError(f"{name}={value!r}: must be an integer >= 1")
        self.horizon_steps = int(horizon_steps)
        self.n_futures = 1 if self.clairvoyant else int(n_futures)
        self.base_interval_steps = int(base_interval_steps)
        self.decide_every_steps = int(decide_every_steps)
        self.env = None
        self.rng = np.random.default_rng()
        self.t = 0
        self.simulated_steps = 0
        self.last_gain = float("nan")  # return(calibrate now) - return(wait) at the last decision

    def bind(self, env) -> None:
        """The env this policy plans on (a :class:`UWBCalibrationParallelEnv`, or the scheduler
        env's ``.parallel``); it must be simulated (a hardware env has no state to copy)."""
        env = getattr(env, "parallel", env)
        if not getattr(env, "deterministic", False) or not getattr(env, "ground_truth", False):
            raise ValueError("lookahead: needs a simulated env with ground truth (not hardware)")
        self.env = env

    def reset(self, seed: int | None = None) -> None:
        # Its own stream, distinct from the env's even when both are given the same seed.
        self.rng = np.random.default_rng([0x100CA, seed] if seed is not None else None)
        self.t = 0

    def act(self, observations, infos):
        if self.env is None:
            raise RuntimeError("lookahead: call bind(env) before the episode (the evaluation harness does)")
        self.t += 1
        env = self.env
        if env.system.world.round is not None:  # requests are ignored while a round runs
            return {a: 0 for a in observations}
        request = self._plan(env) if self.t % self.decide_every_steps == 0 else False
        return {a: int(request) for a in observations}

    # -- planning ---------------------------------------------------------------------------------
    def _base_wants(self, env) -> bool:
        steps = env.system.steps_since_calibration
        return env.system.world.round is None and bool(steps.max() >= self.base_interval_steps)

    def _plan(self, env) -> bool:
        seeds = self.rng.integers(0, 2**63, self.n_futures)
        totals = np.zeros((2, 2))  # [now, wait] x [reward, steps], summed over futures
        for seed in seeds:
            totals[0] += self._simulate(env, True, seed)
            totals[1] += self._simulate(env, False, seed)
        rate = totals[:, 0] / np.maximum(totals[:, 1], 1)
        self.last_gain = float(rate[0] - rate[1])  # reward per step: calibrate now - wait
        return self.last_gain > 0

    def _clone(self, env, seed):
        # Shared read-only parts are not copied (speed); the real generator maps to a fresh one.
        memo = {id(env.config): env.config, id(env.observation_spaces): env.observation_spaces,
                id(env.action_spaces): env.action_spaces}
        memo[id(env.np_random)] = np.random.default_rng(seed)
        sim = copy.deepcopy(env, memo)
        if sim.system.world.rng is env.np_random:  # a second handle on the real stream: refuse
            raise RuntimeError("lookahead: the copy still draws from the real env's generator")
        return sim

    def _simulate(self, env, calibrate_now: bool, seed) -> tuple[float, int]:
        """(total reward, steps) of one branch up to the end of its first calibration cycle."""
        sim = self._clone(env, seed)
        total, steps, rounds = 0.0, 0, 0
        while steps < self.horizon_steps and sim.agents:
            # "wait" holds off until the next decision point; both continue with the base heuristic.
            request = calibrate_now if steps == 0 else (steps >= self.decide_every_steps and self._base_wants(sim))
            if request and sim.system.world.round is None:
                rounds += 1
                if rounds == 2:  # the next cycle starts: this branch's cycle is complete
                    break
            _, rewards, _, _, _ = sim.step({a: int(request) for a in sim.agents})
            total += next(iter(rewards.values()))
            steps += 1
        self.simulated_steps += steps
        return total, steps


class ClairvoyantPolicy(LookaheadPolicy):
    """OPTIMISTIC BOUND: the lookahead simulated on the real future's random stream (see the
    module docstring). Not a deployable plan, not even a fair planner."""

    clairvoyant = True

    def _clone(self, env, seed):
        memo = {id(env.config): env.config, id(env.observation_spaces): env.observation_spaces,
                id(env.action_spaces): env.action_spaces}
        return copy.deepcopy(env, memo)  # the generator's state is copied: the real future


class RolloutPolicy(LookaheadPolicy):
    """GROUND TRUTH reference: one step of policy improvement over a base heuristic (rollout).

    The base is any scheduler spec of the registry, e.g. the scenario's best tuned heuristic
    (``per_anchor_drift:0.21``), the one the learned scheduler is measured against: what this
    planner gains over it is headroom a scheduler can have. Every ``decide_every_steps`` (no
    round running) it compares, on copies of the true state over ``n_futures`` sampled futures
    (common random numbers; the real generator is never read, as in :class:`LookaheadPolicy`),
    three moves, each followed by the base for ``horizon_steps`` steps in total: the base's own,
    a team round now, and no request until the next decision point ("wait"; not simulated when
    the base itself requested nothing before then in any future: the same branch).

    An alternative is taken only where its summed reward beats the base's in a one-sided paired
    t-test over the futures at level ``alpha`` (the best such one); otherwise the base's move.
    Taking the plain best of a few noisy sums departs on noise: over a base that never
    calibrates, the plain argmax of 8 futures calibrated 4 times in 30 s and lost to its base
    by 15 %. A ground-truth policy that improves on its base, not a bound: a better planner (or
    a deployable policy) may gain more. Between decisions it follows the base (or holds, after
    choosing to wait); the base sees every step. The team and nothing actions follow the base's
    action mode, which must be the env's. Spec: ``rollout:H@BASE`` (e.g.
    ``rollout:60@per_anchor_drift:0.21``).
    """

    REVISION = 2  # bump when the planning changes: benchmarks reuse a stored reference only at the same one

    def __init__(self, base_spec: str = "fixed:10", horizon_steps: int = 60, n_futures: int = 8,
                 decide_every_steps: int = 10, alpha: float = 0.025, dt_s: float = 0.2):
        from scipy.stats import t as student_t

        from uwb_env.agents.registry import make_policy

        super().__init__(horizon_steps=horizon_steps, n_futures=n_futures, decide_every_steps=decide_every_steps)
        if self.n_futures < 2:
            raise ValueError(f"n_futures={n_futures!r}: must be >= 2 (the test of a departure needs a spread)")
        if not 0.0 < alpha < 0.5:
            raise ValueError(f"alpha={alpha!r}: must be in (0, 0.5)")
        self.alpha = float(alpha)
        self._t_quantile = float(student_t.ppf(1.0 - alpha, self.n_futures - 1))
        self.base_spec = base_spec
        self.base = make_policy(base_spec, dt_s)
        if getattr(self.base, "uses_ground_truth", False):
            raise ValueError(f"base_spec={base_spec!r}: the base must be a deployable scheduler (no ground truth)")
        self.action_mode = getattr(self.base, "action_mode", None)
        # per_anchor mode: 0 nothing, 2 team round; the binary mode: 0 / 1 (a team request)
        self._team = 2 if self.action_mode == "per_anchor" else 1
        self.reset()

    def describe(self) -> dict:
        """What identifies this planner's answers (a stored reference is reused only on a match)."""
        return {"revision": self.REVISION, "base": self.base_spec, "horizon_steps": self.horizon_steps,
                "n_futures": self.n_futures, "decide_every_steps": self.decide_every_steps, "alpha": self.alpha}

    def bind(self, env) -> None:
        super().bind(env)
        mode = self.env.config.action_mode
        if mode != (self.action_mode or "calibrate"):
            raise ValueError(f"rollout: the env's action_mode={mode!r} is not its base's "
                             f"({self.action_mode or 'calibrate'!r}, {self.base_spec!r})")

    def reset(self, seed: int | None = None) -> None:
        super().reset(seed)
        self.base.reset(seed)
        self._hold = 0
        self.simulated_steps = 0
        self.last_gain = float("nan")  # the estimated gain of the last decision's departure (0: none)
        self.last_totals: dict = {}  # per simulated move, the summed reward of each future
        self.decisions = {"base": 0, "team": 0, "wait": 0}

    def act(self, observations, infos):
        if self.env is None:
            raise RuntimeError("rollout: call bind(env) before the episode (the evaluation harness does)")
        self.t += 1
        base = self.base.act(observations, infos)  # every step: the base keeps its own state
        if self.env.system.world.round is not None:  # requests are ignored while a round runs
            return base
        if self._hold > 0:
            self._hold -= 1
            return {a: 0 for a in observations}
        if self.t % self.decide_every_steps:
            return base
        moves = {"base": base, "team": {a: self._team for a in observations}, "wait": {a: 0 for a in observations}}
        move = self._decide(moves)
        if move == "wait":
            self._hold = self.decide_every_steps - 1
        return moves[move]

    def _decide(self, moves: dict) -> str:
        """The move to take of ``moves`` (base, team, wait: their first actions)."""
        env, base = self.env, moves["base"]
        seeds = self.rng.integers(0, 2**63, self.n_futures)
        runs = [self._simulate_move(env, base, False, s) for s in seeds]
        totals = {"base": np.array([r[0] for r in runs])}
        base_asked = any(r[1] for r in runs)  # the base requested before the next decision somewhere
        for name in ("team", "wait"):
            if moves[name] == base and not (name == "wait" and base_asked):
                continue  # the base's own branch in every future
            totals[name] = np.array([self._simulate_move(env, moves[name], name == "wait", s)[0] for s in seeds])
        self.last_totals = totals
        best, self.last_gain = "base", 0.0
        # team, then wait: a one-sided paired t-test over the futures (common random numbers)
        for name in [n for n in totals if n != "base"]:
            diff = totals[name] - totals["base"]
            gain = float(diff.mean())
            threshold = self._t_quantile * float(diff.std(ddof=1)) / np.sqrt(len(diff))
            if gain > max(threshold, 1e-9) and gain > self.last_gain:
                best, self.last_gain = name, gain
        self.decisions[best] += 1
        return best

    def _simulate_move(self, env, first: dict, wait: bool, seed) -> tuple[float, bool]:
        """Summed reward of ``first`` now, then the base (after holding until the next decision
        point if ``wait``), over ``horizon_steps`` steps of a copy of the true state; and whether
        the base asked for anything before the next decision point."""
        sim = self._clone(env, seed)
        base = copy.deepcopy(self.base)
        total, actions, asked, steps = 0.0, first, False, 0
        while steps < self.horizon_steps and sim.agents:
            observations, rewards, _, _, infos = sim.step(actions)
            total += next(iter(rewards.values()))
            steps += 1
            actions = base.act(observations, infos)  # the base sees every step, as in the real episode
            if steps < self.decide_every_steps:
                asked = asked or any(actions.values())
                if wait:
                    actions = {a: 0 for a in actions}
        self.simulated_steps += steps
        return total, asked

"""PettingZoo ParallelEnv: anchor robots decide when the team calibrates.

## Description
N mobile anchor robots localize M tags by UWB ranging. Anchors know their own positions only
from the embedded autocalibration solver (at calibration rounds) and their odometry (in
between), which drifts. A calibration round re-estimates every anchor, but lasts several steps
(the fitted DWM1001 timing: ~0.9 s for 4 anchors at K=5) during which the channel is busy and
tags keep their last fix. The agents decide *when* to calibrate.

## Agents
``anchor_0`` ... ``anchor_{N-1}``; all act every step; nobody leaves before the episode ends.

## Action space
``calibrate`` mode (default): ``Discrete(2)``: 0 = no request, 1 = request a calibration. The
``trigger`` rule turns requests into a round: ``any`` (default), ``majority`` or ``all``.
Requests while a round runs are ignored and counted in ``infos["requests_ignored"]``.
``per_anchor`` mode: ``Discrete(3)``: 0 = nothing, 1 = re-locate me (a per-anchor round: this
anchor ranges to the others, 1/n of a team round's channel time, and solves its own position
with theirs and their covariances as known and its odometry as the prior), 2 = request a team
round (``trigger`` rule as above). A triggered team round wins; otherwise the requesting anchor
with the largest predicted error gets the channel. ``infos["round_anchor"]`` names the anchor of
a per-anchor round that started (-1 otherwise).
``calibrate_and_move`` mode: ``Discrete(2 * (H + 1))``: ``a // (H + 1)`` is the request bit,
``a % (H + 1)`` picks one of H headings (at ``move_speed_mps``) or H = stop; this replaces
the scripted motion of the anchors.

## Observation space
``Box(low, high, (dim + 8,), float32)`` per anchor, clipped into the declared bounds:

| index | meaning | unit |
| --- | --- | --- |
| 0..dim-1 | the anchor's estimated position (localization frame) | m |
| dim | time since the last calibration | s |
| dim+1 | predicted position std (calibration covariance + drift model of the odometry) | m |
| dim+2 | position std from the last calibration's covariance | m |
| dim+3 | RMS residual of the last calibration | m |
| dim+4 | mean RMS residual of the tag fixes over the last ``residual_window_steps`` | m |
| dim+5 | this anchor's mean absolute range residual in those tag fixes | m |
| dim+6 | 1 while a calibration round runs | - |
| dim+7 | progress of the running round | 0..1 |

## Rewards
One team reward, the same for every anchor:
``-(tag_error_weight * mean tag error + anchor_error_weight * mean anchor error
+ calibration_time_weight * fraction of the step spent calibrating
+ calibration_start_cost * [round started])``. Errors are in metres, measured after the rigid
alignment of the true anchors onto their estimates (range-only calibration cannot observe
the drift of the whole frame, and the paper measures positions relative to the anchors);
``infos`` also carry the fixed-frame errors and the paper's rotation error. Each term is in
``infos[agent]["reward_<term>"]``.

## Info
``infos[agent]`` has the same keys and types at ``reset`` and after every step, all numbers,
booleans or fixed-shape arrays (no None, no strings, no nested dicts), so clients that stack
infos into tensors (TorchRL, vector envs) work. PettingZoo's convention is one dict per agent:
the team-level keys (everything except ``anchor_error_m``) are the same values in every agent's
dict; read them from any one agent.

| key | type | meaning |
| --- | --- | --- |
| ``anchor_error_m`` | float | this anchor's position error (aligned frame), m |
| ``mean_tag_error_m``, ``mean_anchor_error_m`` | float | team means (aligned frame), m |
| ``mean_tag_error_fixed_frame_m``, ``mean_anchor_error_fixed_frame_m`` | float | the same in the fixed frame, m |
| ``rotation_error_rad`` | float | the paper's rotation error |
| ``tag_errors_m`` | (n_tags,) float array | per tag error, m |
| ``tag_status`` | (n_tags,) int array | 0 ok, 1 ambiguous (mirror fits too), 2 no fix, 3 poor fit |
| ``n_tags_ambiguous``, ``n_tags_poor_fit`` | int | tags with status 1 / 3 (3: ranges the anchors cannot explain) |
| ``calibration_count``, ``anchor_round_count`` | int | team / per-anchor rounds finished |
| ``time_calibrating_s``, ``time_s`` | float | channel time spent calibrating; episode time |
| ``calibrating`` | bool | a round runs |
| ``calibrating_fraction`` | float | fraction of the last step spent calibrating (0 at reset) |
| ``round_started``, ``round_finished`` | bool | in the last step |
| ``calibration_failed`` | bool | the last round failed (the reason: ``env.calibration_error``, "" otherwise) |
| ``calibration_fit`` | int | last team round: 0 ok, 1 poor fit (cov. x chi2/dof), 2 not converged (odometry kept) |
| ``calibration_ambiguous`` | bool | another shape fits those ranges as well (the prior chose) |
| ``calibration_chi2_per_dof`` | float | its reduced chi-square (1 = residuals as the range model predicts) |
| ``requests_ignored`` | int | requests made while a round ran |
| ``round_anchor`` | int | anchor of a per-anchor round that started, -1 otherwise |
| ``reward_`` + ``tag_error``, ``anchor_error``, ``calibration_time``, ``calibration_start`` | float | (0 at reset) |
| ``ground_truth`` | bool | False on hardware (truth-based keys are NaN) |

## Starting state
Anchors near the corners of the area, tags inside their polygon; a first calibration (the
paper's rules) runs during ``reset`` and defines the localization frame.

## Episode end
Truncation after ``max_cycles`` steps. There is no terminal state (termination stays False).

## Arguments
``uwb_env.parallel_env(config=None, render_mode=None, backend=None, **overrides)``: ``config``
an :class:`~uwb_env.config.EnvConfig` or dict; keyword overrides merge into it (unknown keys
raise :class:`~uwb_env.config.ConfigError`). ``backend``: a
:class:`~uwb_env.hardware.backend.HardwareWorld` to run on real (or emulated) DWM1001 devices
(see ``uwb_env.hardware.connect``): then there is no ground truth (truth-based ``infos`` are
NaN, ``infos[a]["ground_truth"]`` is False), the reward's tag/anchor terms become the
residual proxy, steps run in wall-clock time, and ``env.deterministic`` is False.

## Version history
v0: initial release.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.utils import EzPickle, seeding
from pettingzoo import ParallelEnv

from uwb_env.config import EnvConfig, UnknownConfigKeyError
from uwb_env.rewards import REWARD_TERMS
from uwb_env.system import LocalizationSystem

_PLAIN_INTS = (int, np.int64, np.int32)  # bool is a subclass of int, not the same type: refused
# the reward's four terms are in infos at reset (all zero) as after every step
_ZERO_TERMS = dict.fromkeys(REWARD_TERMS, 0.0)


def make_config(config: EnvConfig | dict | None, overrides: dict[str, Any]) -> EnvConfig:
    if config is None:
        config = EnvConfig()
    elif isinstance(config, dict):
        config = EnvConfig.from_dict(config)
    elif not isinstance(config, EnvConfig):
        raise TypeError(f"config={config!r}: expected EnvConfig, dict or None")
    unknown = [k for k in overrides if k not in EnvConfig.__dataclass_fields__]
    if unknown:  # worded as Python words it: TorchRL's GymEnv retries without `frameskip` on this text
        raise UnknownConfigKeyError(
            unknown[0], overrides[unknown[0]],
            f"__init__() got an unexpected keyword argument {unknown[0]!r} "
            f"(EnvConfig keys: {sorted(EnvConfig.__dataclass_fields__)})")
    return config.replace(**overrides) if overrides else config


class UWBCalibrationParallelEnv(ParallelEnv, EzPickle):
    """See the module docstring for spaces, reward, termination and arguments."""

    metadata = {"render_modes": ["human", "rgb_array"], "name": "uwb_calibration_v0", "is_parallelizable": True,
                "render_fps": 10}

    def __init__(self, config: EnvConfig | dict | None = None, render_mode: str | None = None, backend=None,
                 **overrides: Any):
        EzPickle.__init__(self, config, render_mode, backend, **overrides)
        self.config = make_config(config, overrides)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode={render_mode!r}: must be one of {self.metadata['render_modes']}")
        self.render_mode = render_mode
        self.system = LocalizationSystem(self.config, world=backend)
        # On hardware there is no ground truth and no reproducibility across runs.
        self.ground_truth = self.system.ground_truth
        self.deterministic = backend is None
        n = self.config.sim.n_anchors
        self.possible_agents = [f"anchor_{i}" for i in range(n)]
        self.agents: list[str] = []
        low, high = self.system.feature_bounds()
        obs_space = spaces.Box(low, high, dtype=np.float32)
        heads = self.config.move_headings
        n_actions = {"calibrate": 2, "per_anchor": 3}.get(self.config.action_mode, 2 * (heads + 1))
        act_space = spaces.Discrete(n_actions)
        self.observation_spaces = {a: obs_space for a in self.possible_agents}
        self.action_spaces = {a: act_space for a in self.possible_agents}
        self._heading_table = np.linspace(-np.pi, np.pi, heads, endpoint=False)
        self.np_random, _ = seeding.np_random(None)
        self._renderer = None
        self.history: dict[str, list[float]] = {}
        self.calibration_error = ""  # why the last round failed ("" when it did not)

    # EzPickle's state is only the constructor's arguments, so copy.deepcopy and pickle gave a
    # fresh, un-reset env. A simulated env copies its whole state instead (mid-episode copies
    # continue identically, generator included); one on hardware still rebuilds from arguments.
    def __getstate__(self):
        if not self.deterministic:
            return EzPickle.__getstate__(self)
        return {k: v for k, v in self.__dict__.items() if k != "_renderer"} | {"_renderer": None}

    def __setstate__(self, state):
        if "system" not in state:  # the arguments only (an env on hardware)
            EzPickle.__setstate__(self, state)
        else:
            self.__dict__.update(state)

    def observation_space(self, agent: str) -> spaces.Space:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space:
        return self.action_spaces[agent]

    # -- API ------------------------------------------------------------------------------------
    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self.np_random, _ = seeding.np_random(seed)
        self.system.reset(self.np_random)
        self.agents = list(self.possible_agents)
        self.num_steps = 0
        self.history = {"tag_error_m": [], "anchor_error_m": [], "calibrating": []}
        self._record(0.0)
        report = None
        if self.render_mode == "human":
            self.render()
        return self._observations(), self._infos(report, {})

    def step(self, actions: dict[str, Any]):
        if not self.agents:
            raise RuntimeError("step() called on a finished episode: call reset() first")
        requests, moves = self._decode(actions)
        if self.config.action_mode == "per_anchor":
            report = self.system.step(requests == 2, None, requests == 1)
        else:
            report = self.system.step(requests, moves)
        self.num_steps += 1
        terms = self.system.reward_terms(report)
        reward = float(sum(terms.values()))
        truncated = self.num_steps >= self.config.max_cycles
        obs = self._observations()
        infos = self._infos(report, terms)
        rewards = {a: reward for a in self.agents}
        terminations = {a: False for a in self.agents}
        truncations = {a: truncated for a in self.agents}
        self._record(report.calibrating_fraction)
        if truncated:
            self.agents = []
        if self.render_mode == "human":
            self.render()
        return obs, rewards, terminations, truncations, infos

    def render(self):
        if self.render_mode is None:
            return None
        if self._renderer is None:
            from uwb_env.env.render import Renderer

            self._renderer = Renderer(self.config, self.render_mode)
        return self._renderer.draw(self.system, self.history)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # -- helpers --------------------------------------------------------------------------------
    def _decode(self, actions: dict[str, Any]):
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise KeyError(f"actions: missing entries for agents {missing}")
        space = self.action_spaces[self.possible_agents[0]]
        n_actions = int(space.n)
        given = [actions[a] for a in self.possible_agents]
        if all(type(v) in _PLAIN_INTS and 0 <= v < n_actions for v in given):  # the usual case, checked fast
            values = np.array(given, dtype=np.int64)
        else:
            values = np.empty(len(given), dtype=np.int64)
            for i, (agent, act) in enumerate(zip(self.possible_agents, given, strict=True)):
                if isinstance(act, np.ndarray) and act.shape == ():
                    act = act.item()
                if isinstance(act, bool) or not isinstance(act, (int, np.integer)) or not 0 <= act < n_actions:
                    raise ValueError(f"actions[{agent!r}]={act!r}: not in {space}")
                values[i] = act
        if self.config.action_mode == "calibrate":
            return values == 1, None
        if self.config.action_mode == "per_anchor":
            return values, None
        per = self.config.move_headings + 1
        requests, move = values // per == 1, values % per
        stop = move == self.config.move_headings
        heading = self._heading_table[np.minimum(move, self.config.move_headings - 1)]
        speed = np.where(stop, 0.0, self.config.move_speed_mps)
        return requests, np.column_stack([heading, speed])

    def _observations(self) -> dict[str, np.ndarray]:
        feats = self.system.anchor_features()
        return {a: feats[i] for i, a in enumerate(self.agents)}

    def _infos(self, report, terms) -> dict[str, dict]:
        s = self.system
        self.calibration_error = (report.calibration_failed or "") if report else ""
        anchor_err = s.anchor_errors_m()
        tag_err = s.tag_errors_m()
        n_tags = max(len(tag_err), 1)  # means of no tags are 0
        anchor_errs = anchor_err.tolist()
        shared = {
            "mean_tag_error_m": math.fsum(tag_err.tolist()) / n_tags,
            "mean_anchor_error_m": math.fsum(anchor_errs) / len(anchor_errs),
            "mean_tag_error_fixed_frame_m": math.fsum(s.tag_errors_m("fixed").tolist()) / n_tags,
            "mean_anchor_error_fixed_frame_m": math.fsum(s.anchor_errors_m("fixed").tolist()) / len(anchor_errs),
            "rotation_error_rad": s.rotation_error_rad(),
            "tag_errors_m": tag_err,
            "calibration_count": s.calibration_count,
            "time_calibrating_s": s.time_calibrating_s,
            "time_s": s.world.time_s,
            "calibrating": s.world.round is not None,
            "calibrating_fraction": float(report.calibrating_fraction) if report else 0.0,
            "round_started": bool(report.round_started) if report else False,
            "round_finished": bool(report.round_finished) if report else False,
            # a flag (the message is env.calibration_error: TorchRL turns every info value into a tensor)
            "calibration_failed": bool(report and report.calibration_failed),
            # the last team round's verdict: 0 ok, 1 poor fit (applied, covariance scaled by
            # chi2/dof), 2 not converged (not applied); a shape the prior had to choose
            "calibration_fit": int(s.calibration_fit),
            "calibration_ambiguous": bool(s.calibration_ambiguous),
            "calibration_chi2_per_dof": float(s.calibration_chi2_per_dof),
            "requests_ignored": report.requests_ignored if report else 0,
            "round_anchor": report.round_anchor if report else -1,
            # per tag: 0 ok, 1 ambiguous (its mirror fits the ranges as well), 2 no fix, 3 poor
            # fit (the ranges reject the fix at the fit test's level; the position is kept)
            "tag_status": s.tag_status.copy(),
            "n_tags_ambiguous": int(np.count_nonzero(s.tag_status == 1)),
            "n_tags_poor_fit": int(np.count_nonzero(s.tag_status == 3)),
            "anchor_round_count": s.anchor_round_count,
            # flat float keys, zero at reset (no nested dicts: TorchRL and vector envs stack infos)
            **{f"reward_{k}": float(v) for k, v in {**_ZERO_TERMS, **terms}.items()},
            # False on hardware: the truth-based keys above are NaN and the reward's tag and
            # anchor terms are the residual proxy (see LocalizationSystem.reward_terms).
            "ground_truth": s.ground_truth,
        }
        return {a: {**shared, "anchor_error_m": e} for a, e in zip(self.agents, anchor_errs, strict=True)}

    def _record(self, calibrating_fraction: float) -> None:
        if self.render_mode is None:  # traces exist only for rendering: no cost otherwise
            return
        self.history["tag_error_m"].append(float(self.system.tag_errors_m().mean()) if self.system.n_tags else 0.0)
        self.history["anchor_error_m"].append(float(self.system.anchor_errors_m().mean()))
        self.history["calibrating"].append(calibrating_fraction)

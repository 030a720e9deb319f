"""SB3 ``VecEnv`` over PettingZoo ParallelEnv copies: one slot per (copy, anchor).

Every anchor of every copy is one SB3 "environment", so one policy is shared by all anchors
(parameter sharing) and sees each anchor's own observation. Unlike SuperSuit's conversion,
this keeps ``PPO(seed=...)`` working (``seed()`` seeds each copy's ``reset``) and reports the
time limit as truncation: ``dones[i]`` is True with ``infos[i]["TimeLimit.truncated"] = True``
and ``infos[i]["terminal_observation"]`` set, so SB3 bootstraps the value at the cut.
Copies reset automatically when their episode ends, as every SB3 VecEnv does.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from uwb_env.agents.per_anchor import team_vote


class ParallelEnvVecEnv(VecEnv):
    def __init__(self, env_fns: Sequence[Callable[[], Any]]):
        self.envs = [fn() for fn in env_fns]
        first = self.envs[0]
        self.agents = list(first.possible_agents)
        for env in self.envs[1:]:
            if list(env.possible_agents) != self.agents:
                raise ValueError("env_fns: every copy must have the same agents")
        self.n_agents = len(self.agents)
        super().__init__(len(self.envs) * self.n_agents, first.observation_space(self.agents[0]),
                         first.action_space(self.agents[0]))
        self._actions: np.ndarray | None = None
        self._obs = np.zeros((self.num_envs, *self.observation_space.shape), dtype=self.observation_space.dtype)

    # -- VecEnv API ------------------------------------------------------------------------------
    def reset(self):
        for k, env in enumerate(self.envs):
            seed = self._seeds[k * self.n_agents]
            obs, infos = env.reset(seed=seed)
            self._store(k, obs)
            for j, agent in enumerate(self.agents):
                self.reset_infos[k * self.n_agents + j] = infos.get(agent, {})
        self._reset_seeds()
        self._reset_options()
        return self._obs.copy()

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions).reshape(len(self.envs), self.n_agents)

    def step_wait(self):
        rewards = np.zeros(self.num_envs, dtype=np.float32)
        dones = np.zeros(self.num_envs, dtype=bool)
        infos: list[dict] = [{} for _ in range(self.num_envs)]
        for k, env in enumerate(self.envs):
            acts = {agent: int(self._actions[k, j]) for j, agent in enumerate(self.agents)}
            obs, rew, terms, truncs, step_infos = env.step(acts)
            base = k * self.n_agents
            ended = False
            for j, agent in enumerate(self.agents):
                i = base + j
                rewards[i] = rew[agent]
                term, trunc = bool(terms[agent]), bool(truncs[agent])
                info = dict(step_infos.get(agent, {}))
                if term or trunc:
                    ended = True
                    dones[i] = True
                    info["TimeLimit.truncated"] = trunc and not term
                    info["terminal_observation"] = obs[agent]
                infos[i] = info
            if ended:
                obs, reset_infos = env.reset()
                for j, agent in enumerate(self.agents):
                    self.reset_infos[base + j] = reset_infos.get(agent, {})
            self._store(k, obs)
        return self._obs.copy(), rewards, dones, infos

    def close(self) -> None:
        for env in self.envs:
            env.close()

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self.envs[i // self.n_agents], attr_name) for i in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        for k in sorted({i // self.n_agents for i in self._get_indices(indices)}):
            setattr(self.envs[k], attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        return [getattr(self.envs[i // self.n_agents], method_name)(*method_args, **method_kwargs)
                for i in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def _store(self, k: int, obs: dict[str, np.ndarray]) -> None:
        for j, agent in enumerate(self.agents):
            self._obs[k * self.n_agents + j] = obs[agent]


class BatchedSchedulerVecEnv(VecEnv):
    """SB3 ``VecEnv`` over :class:`uwb_env.batch.BatchedSystem`: ``num_envs`` scheduler copies
    stepped together in numpy. All copies truncate together; SB3 gets ``dones`` with
    ``TimeLimit.truncated`` and ``terminal_observation``, then the reset observations."""

    def __init__(self, num_envs: int, env_config: dict | None = None):
        from uwb_env.env.vector_env import CalibrationSchedulingVectorEnv

        # SB3 wants the terminal observation beside the reset one: SAME_STEP
        self.venv = CalibrationSchedulingVectorEnv(num_envs, config=env_config, autoreset_mode="SameStep")
        super().__init__(num_envs, self.venv.single_observation_space, self.venv.single_action_space)
        self._actions = None

    def reset(self):
        obs, _ = self.venv.reset(seed=self._seeds[0])
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions).reshape(self.num_envs)

    def step_wait(self):
        obs, rewards, terms, truncs, info = self.venv.step(self._actions)
        dones = terms | truncs
        infos = [{"mean_tag_error_m": float(info["mean_tag_error_m"][i])} for i in range(self.num_envs)]
        if dones.any():
            for i in range(self.num_envs):
                infos[i]["TimeLimit.truncated"] = bool(truncs[i] and not terms[i])
                infos[i]["terminal_observation"] = info["final_obs"][i]
        return obs, rewards.astype(np.float32), dones, infos

    def close(self) -> None:
        pass

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self.venv, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        raise NotImplementedError("the batched env has no per-copy env objects")

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]


class AnchorSetVecEnv(VecEnv):
    """SB3 ``VecEnv`` for the team-size-invariant per-anchor scheduler: one slot per anchor of
    each training copy (copy k has ``distribution.team_sizes[k]`` anchors for good), each slot
    observing :func:`uwb_env.agents.anchor_set.anchor_set_features` and choosing a
    ``per_anchor`` action. Every episode of a copy is a new scenario (and base threshold of the
    residual's rule) drawn from ``distribution``
    (a ``training.train_anchor_set.ScenarioDistribution``) with ``rng``, on the seeds
    ``seed_base, seed_base + 1, ...`` (mod ``seed_span``: the training seed range)."""

    render_mode = None

    def __init__(self, distribution, rng: np.random.Generator, seed_base: int, seed_span: int):
        from gymnasium import spaces
        from uwb_env.agents.anchor_set import DEFAULT_BASE_THRESHOLD_M, N_FEATURES

        self.distribution, self.rng = distribution, rng
        self.seed_base, self.seed_span, self.episodes = seed_base, seed_span, 0
        self.sizes = [int(n) for n in distribution.team_sizes]
        self.offsets = np.concatenate([[0], np.cumsum(self.sizes)])
        obs_space = spaces.Box(-np.inf, np.inf, (N_FEATURES,), np.float32)
        super().__init__(int(self.offsets[-1]), obs_space, spaces.Discrete(3))
        self.envs: list = [None] * len(self.sizes)
        self.dts = [0.2] * len(self.sizes)
        # the residual's base rule threshold of each copy, drawn per episode
        self.base_thresholds = [DEFAULT_BASE_THRESHOLD_M] * len(self.sizes)
        self._obs = np.zeros((self.num_envs, N_FEATURES), dtype=np.float32)
        self._actions = None

    def _new_episode(self, k: int):
        from uwb_env.env.parallel_env import UWBCalibrationParallelEnv

        overrides = self.distribution.sample(self.sizes[k], self.rng)
        self.base_thresholds[k] = self.distribution.sample_base_threshold(self.rng)
        env = UWBCalibrationParallelEnv(overrides)
        self.envs[k], self.dts[k] = env, env.config.sim.dt_s
        seed = (self.seed_base + self.episodes) % self.seed_span
        self.episodes += 1
        obs, _ = env.reset(seed=seed)
        return obs

    def _store(self, k: int, obs: dict) -> None:
        from uwb_env.agents.anchor_set import from_observations

        _, rows = from_observations(obs, self.dts[k], self.base_thresholds[k])
        self._obs[self.offsets[k]: self.offsets[k + 1]] = rows

    def reset(self):
        for k in range(len(self.sizes)):
            self._store(k, self._new_episode(k))
        return self._obs.copy()

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions).reshape(self.num_envs)

    def step_wait(self):
        rewards = np.zeros(self.num_envs, dtype=np.float32)
        dones = np.zeros(self.num_envs, dtype=bool)
        infos: list[dict] = [{} for _ in range(self.num_envs)]
        for k, env in enumerate(self.envs):
            lo, hi = self.offsets[k], self.offsets[k + 1]
            agents = env.agents
            # team-round requests are votes, as the deployed policy casts them (AnchorSetPolicy.act)
            voted = team_vote(self._actions[lo:hi])
            actions = {a: int(x) for a, x in zip(agents, voted, strict=True)}
            obs, rew, terms, truncs, _ = env.step(actions)
            rewards[lo:hi] = rew[agents[0]]  # the team reward, the same for every anchor
            self._store(k, obs)
            if any(terms.values()) or any(truncs.values()):
                trunc = not any(terms.values())
                dones[lo:hi] = True
                for i in range(lo, hi):
                    infos[i] = {"TimeLimit.truncated": trunc, "terminal_observation": self._obs[i].copy()}
                env.close()
                self._store(k, self._new_episode(k))
        return self._obs.copy(), rewards, dones, infos

    def close(self) -> None:
        for env in self.envs:
            if env is not None:
                env.close()

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        return [None for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

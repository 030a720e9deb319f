"""Team-size-invariant features for a per-anchor scheduler shared by all anchors, and the
residual policy on top of the per-anchor threshold heuristic.

Each anchor decides about itself (``per_anchor`` actions: nothing / re-locate me / team round)
from its own features and a permutation-invariant summary of the others' (mean and max), so
one trained model runs on any team size, in 2D or 3D. Positions are left out: they are
coordinates in a frame the first calibration chose, not information about staleness.

The policy is a *residual* over the per-anchor threshold rule (``agents/per_anchor.py``) with
a threshold ``base_threshold_m`` that is tuned per deployment like any heuristic: the rule's
action enters the features as a one-hot and is added to the policy's logits with weight
``prior_logit`` (:class:`uwb_env.agents.prior_policy.PriorLogitsPolicy`), so an untrained
policy acts exactly as the rule and training learns where to depart from it. A scheduler that
starts from the best tuned heuristic cannot lose to it by forgetting what it already knew;
departures have to pay for themselves in the return. Team-round requests are votes
(``per_anchor.team_vote``): a round starts when half of the team asks, the rule's own quorum.

Layout of one anchor's row (``ANCHOR_SET_FIELDS``):

| columns | meaning |
| --- | --- |
| 0..7 | the anchor's own ``OBS_FIELDS`` (time since calibration ... round progress) |
| 8..13 | mean over the other anchors of the first six ``OBS_FIELDS`` |
| 14..19 | max over the other anchors of the same |
| 20 | share of the other anchors whose predicted std is below this anchor's (0..1) |
| 21 | team size N |
| 22 | step length dt (s) |
| 23 | the base rule's threshold (m) |
| 24 | own predicted std over that threshold |
| 25..27 | the base rule's action, one-hot (nothing, re-locate me, team round); never normalized |
"""

from __future__ import annotations

import numpy as np

from uwb_env.agents.per_anchor import check_measure, team_vote, threshold_actions
from uwb_env.system import OBS_FIELDS

_SUMMARIZED = OBS_FIELDS[:6]  # the team-level flags (calibrating, progress) are the same for all
ANCHOR_SET_FIELDS = (
    tuple(OBS_FIELDS)
    + tuple(f"others_mean_{f}" for f in _SUMMARIZED)
    + tuple(f"others_max_{f}" for f in _SUMMARIZED)
    + ("rank_predicted_std", "n_anchors", "dt_s", "base_threshold_m", "predicted_std_over_base_threshold",
       "base_nothing", "base_relocate_me", "base_team_round")
)
N_FEATURES = len(ANCHOR_SET_FIELDS)
N_ACTIONS = 3
N_RAW = N_ACTIONS  # the last columns (the base action's one-hot) bypass the normalization
_PREDICTED = OBS_FIELDS.index("predicted_position_std_m")
_CALIBRATION = OBS_FIELDS.index("calibration_position_std_m")
DEFAULT_BASE_THRESHOLD_M = 0.3


def anchor_set_features(own: np.ndarray, dt_s: float, base_threshold_m=DEFAULT_BASE_THRESHOLD_M,
                        base_measure: str = "total") -> np.ndarray:
    """(..., N, len(OBS_FIELDS)) per-anchor env features (positions already dropped) ->
    (..., N, N_FEATURES) float32. ``base_threshold_m``: the residual's base rule threshold, a
    float or one per team (shape (...)); ``base_measure``: what the rule compares with it
    (``per_anchor.threshold_actions``: "total" or "drift"). Needs N >= 2 (a team has at least
    3 anchors)."""
    given = np.asarray(own)
    own = given.astype(np.float64)
    n = own.shape[-2]
    if n < 2:
        raise ValueError(f"own: needs at least 2 anchors, got shape {own.shape}")
    thr = np.broadcast_to(np.asarray(base_threshold_m, dtype=np.float64), own.shape[:-2])
    if not (np.isfinite(thr) & (thr > 0)).all():
        raise ValueError(f"base_threshold_m={base_threshold_m!r}: must be finite and > 0")
    part = own[..., : len(_SUMMARIZED)]
    total = part.sum(-2, keepdims=True)
    others_mean = (total - part) / (n - 1)
    # max over the others: the team max, or the second largest for the anchor holding it
    order = np.sort(part, axis=-2)
    first, second = order[..., -1:, :], order[..., -2:-1, :]
    others_max = np.where(part >= first, second, first)
    pred = own[..., _PREDICTED]
    rank = (pred[..., None, :] < pred[..., :, None]).sum(-1) / (n - 1)
    shape = own.shape[:-1]
    thr_rows = np.broadcast_to(thr[..., None], shape)
    # the rule on the stds as given (float32 observations), exactly as the heuristic compares them
    base = np.eye(N_ACTIONS)[threshold_actions(given[..., _PREDICTED], given[..., _CALIBRATION], base_threshold_m,
                                               measure=base_measure)]
    return np.concatenate(
        [own, others_mean, others_max, rank[..., None], np.full((*shape, 1), float(n)), np.full((*shape, 1), dt_s),
         thr_rows[..., None], (pred / thr_rows)[..., None], base],
        axis=-1,
    ).astype(np.float32)


def from_observations(observations: dict[str, np.ndarray], dt_s: float,
                      base_threshold_m: float = DEFAULT_BASE_THRESHOLD_M,
                      base_measure: str = "total") -> tuple[list[str], np.ndarray]:
    """The ParallelEnv's observation dict -> (agents, (N, N_FEATURES) rows)."""
    agents = list(observations)
    own = np.stack([observations[a][-len(OBS_FIELDS):] for a in agents])
    return agents, anchor_set_features(own, dt_s, base_threshold_m, base_measure)


def normalize_rows(rows: np.ndarray, obs_rms, clip_obs: float, epsilon: float = 1e-8) -> np.ndarray:
    """VecNormalize's observation normalization, except the base action's one-hot (the last
    ``N_RAW`` columns): the prior logits must see exactly 0 or 1."""
    out = np.clip((rows - obs_rms.mean) / np.sqrt(obs_rms.var + epsilon), -clip_obs, clip_obs).astype(np.float32)
    out[..., -N_RAW:] = rows[..., -N_RAW:]
    return out


class AnchorSetPolicy:
    """A trained per-anchor policy shared by all anchors, for any team size (``per_anchor``
    actions): a residual over the per-anchor threshold rule at ``base_threshold_m`` on
    ``base_measure`` (tune both like the heuristics' threshold and rule; the specs
    ``learned:<model>@<threshold>`` and ``learned:<model>@drift:<threshold>`` set them).
    ``AnchorSetPolicy.load(path)`` reads a ``training.train_anchor_set`` output (model.zip,
    vecnormalize.pkl beside it); the harness calls :meth:`configure` with the env config (the
    step length is one of the features)."""

    uses_ground_truth = False
    action_mode = "per_anchor"

    def __init__(self, policy, obs_rms=None, clip_obs: float = 10.0, deterministic: bool = True,
                 dt_s: float = 0.2, epsilon: float = 1e-8, base_threshold_m: float = DEFAULT_BASE_THRESHOLD_M,
                 base_measure: str = "total"):
        self.policy, self.obs_rms, self.clip_obs = policy, obs_rms, clip_obs
        self.deterministic, self.dt_s, self.epsilon = deterministic, dt_s, epsilon
        if not (np.isfinite(base_threshold_m) and base_threshold_m > 0):
            raise ValueError(f"base_threshold_m={base_threshold_m!r}: must be finite and > 0")
        self.base_threshold_m = float(base_threshold_m)
        self.base_measure = check_measure(base_measure)
        self.prior_logit = float(getattr(policy, "prior_logit", 0.0))
        # Deterministic actions are the argmax of the logits: one small MLP, evaluated in numpy
        # (SB3's predict costs ~1-3 ms a step in tensor conversions; this ~20 us, same actions).
        self._layers = _numpy_actor(policy) if deterministic else None

    @classmethod
    def load(cls, path, deterministic: bool = True, base_threshold_m: float = DEFAULT_BASE_THRESHOLD_M,
             base_measure: str = "total") -> AnchorSetPolicy:
        import pickle
        from pathlib import Path

        try:
            from stable_baselines3 import PPO

            import uwb_env.agents.prior_policy  # noqa: F401  (the policy class the model names)
        except ImportError as err:
            raise ImportError("AnchorSetPolicy needs stable-baselines3: pip install 'uwb-env[train]'") from err
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"model path={str(path)!r}: no such file")
        model = PPO.load(str(path), device="cpu")
        if model.observation_space.shape != (N_FEATURES,):
            raise ValueError(f"model path={str(path)!r}: observation shape {model.observation_space.shape} is not "
                             f"the anchor-set features' ({N_FEATURES},); retrain it with training.train_anchor_set")
        stats = path.with_name("vecnormalize.pkl")
        if not stats.is_file():  # the model was trained on normalized features: raw ones would be garbage
            raise FileNotFoundError(f"model path={str(path)!r}: no vecnormalize.pkl beside it (saved by training)")
        with open(stats, "rb") as f:
            vn = pickle.load(f)
        return cls(model.policy, vn.obs_rms if vn.norm_obs else None, vn.clip_obs, deterministic, epsilon=vn.epsilon,
                   base_threshold_m=base_threshold_m, base_measure=base_measure)

    def configure(self, config) -> None:
        self.dt_s = float(config.sim.dt_s)

    def incompatibility(self, config) -> str | None:
        return None  # any team size, 2D or 3D: the features do not depend on either

    def reset(self, seed: int | None = None) -> None:
        pass

    def rows(self, observations: dict[str, np.ndarray]) -> tuple[list[str], np.ndarray]:
        agents, rows = from_observations(observations, self.dt_s, self.base_threshold_m, self.base_measure)
        if self.obs_rms is not None:
            rows = normalize_rows(rows, self.obs_rms, self.clip_obs, self.epsilon)
        return agents, rows

    def act(self, observations, infos) -> dict[str, int]:
        agents, rows = self.rows(observations)
        if self._layers is not None:
            actions = _argmax_logits(self._layers, rows, self.prior_logit)
        else:
            actions, _ = self.policy.predict(rows, deterministic=self.deterministic)
        actions = team_vote(actions)  # as in training (training.vec_env.AnchorSetVecEnv)
        return {a: int(x) for a, x in zip(agents, actions, strict=True)}


def _numpy_actor(policy):
    """[(W, b, tanh?), ...] of an SB3 ActorCriticPolicy's actor (flatten features, the policy
    MLP, the action net), or None when the policy is not of that plain shape."""
    import torch

    layers = []
    try:
        modules = list(policy.mlp_extractor.policy_net) + [policy.action_net]
        if type(policy.features_extractor).__name__ != "FlattenExtractor":
            return None
    except (AttributeError, TypeError):
        return None
    for m in modules:
        if isinstance(m, torch.nn.Linear):
            layers.append([m.weight.detach().numpy().astype(np.float64).T, m.bias.detach().numpy().astype(np.float64),
                           False])
        elif isinstance(m, torch.nn.Tanh) and layers:
            layers[-1][2] = True
        else:
            return None
    return layers


def _argmax_logits(layers, x: np.ndarray, prior_logit: float = 0.0) -> np.ndarray:
    h = np.asarray(x, dtype=np.float64)
    for w, b, tanh in layers:
        h = h @ w + b
        if tanh:
            h = np.tanh(h)
    if prior_logit:
        h = h + prior_logit * np.asarray(x, dtype=np.float64)[..., -N_ACTIONS:]
    return h.argmax(axis=-1)

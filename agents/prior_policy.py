"""SB3 pieces of the residual per-anchor scheduler (``agents/anchor_set.py``).

:class:`PriorLogitsPolicy` adds ``prior_logit`` times the last ``N_ACTIONS`` observation
columns (the base rule's action, one-hot) to the actor's logits. SB3 initializes the action
head with gain 0.01, so an untrained policy takes the base rule's action deterministically and
explores around it with probability about ``2 / (exp(prior_logit) + 2)``.
:class:`PartialVecNormalize` leaves those columns raw: normalized, the one-hot would no
longer select a logit. Importing this module imports torch (training and model loading only).
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.vec_env import VecNormalize

from uwb_env.agents.anchor_set import N_ACTIONS, N_RAW


class PriorLogitsPolicy(ActorCriticPolicy):
    """An ``MlpPolicy`` whose logits are ``action_net(latent) + prior_logit * obs[..., -3:]``."""

    def __init__(self, observation_space, action_space, lr_schedule, *args, prior_logit: float = 3.0, **kwargs):
        if not isinstance(action_space, spaces.Discrete) or action_space.n != N_ACTIONS:
            raise ValueError(f"action_space={action_space!r}: PriorLogitsPolicy needs Discrete({N_ACTIONS})")
        if not np.isfinite(prior_logit) or prior_logit < 0:
            raise ValueError(f"prior_logit={prior_logit!r}: must be finite and >= 0")
        self.prior_logit = float(prior_logit)
        super().__init__(observation_space, action_space, lr_schedule, *args, **kwargs)
        if not self.share_features_extractor:
            raise ValueError("PriorLogitsPolicy: share_features_extractor=False is not supported")

    def _get_constructor_parameters(self) -> dict:
        return {**super()._get_constructor_parameters(), "prior_logit": self.prior_logit}

    def _distribution(self, latent_pi, obs):
        logits = self.action_net(latent_pi) + self.prior_logit * obs[..., -N_ACTIONS:].float()
        return self.action_dist.proba_distribution(action_logits=logits)

    def forward(self, obs, deterministic: bool = False):
        latent_pi, latent_vf = self.mlp_extractor(self.extract_features(obs))
        distribution = self._distribution(latent_pi, obs)
        actions = distribution.get_actions(deterministic=deterministic)
        log_prob = distribution.log_prob(actions)
        return actions.reshape((-1, *self.action_space.shape)), self.value_net(latent_vf), log_prob

    def evaluate_actions(self, obs, actions):
        latent_pi, latent_vf = self.mlp_extractor(self.extract_features(obs))
        distribution = self._distribution(latent_pi, obs)
        return self.value_net(latent_vf), distribution.log_prob(actions), distribution.entropy()

    def get_distribution(self, obs):
        latent_pi = self.mlp_extractor.forward_actor(self.extract_features(obs))
        return self._distribution(latent_pi, obs)


class PartialVecNormalize(VecNormalize):
    """``VecNormalize`` that leaves the last ``N_RAW`` observation columns as they are."""

    def normalize_obs(self, obs):
        out = super().normalize_obs(obs)
        if self.norm_obs:
            out[..., -N_RAW:] = np.asarray(obs)[..., -N_RAW:]
        return out

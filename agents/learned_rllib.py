"""An RLlib checkpoint behind the policy hook (needs the ``cluster`` extra).

``RLlibPolicy.load("runs/rllib/checkpoint")`` restores the RLModule(s) alone (no Ray cluster,
no Algorithm): one ``shared`` module for all anchors, or one module per anchor. Actions are
the argmax of the module's action logits (deterministic) on each anchor's observation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


class RLlibPolicy:
    uses_ground_truth = False

    def __init__(self, modules: dict):
        self.modules = modules

    @classmethod
    def load(cls, checkpoint: str | Path) -> RLlibPolicy:
        try:
            from ray.rllib.core.rl_module.rl_module import RLModule
        except ImportError as err:
            raise ImportError("RLlibPolicy needs Ray RLlib: pip install 'uwb-env[cluster]'") from err
        root = Path(checkpoint) / "learner_group" / "learner" / "rl_module"
        if not root.is_dir():
            raise FileNotFoundError(f"checkpoint={str(checkpoint)!r}: no RLModules under {root}")
        modules = {p.name: RLModule.from_checkpoint(str(p)) for p in sorted(root.iterdir()) if p.is_dir()}
        return cls(modules)

    def reset(self, seed: int | None = None) -> None:
        pass

    def act(self, observations: dict[str, np.ndarray], infos: dict[str, dict]) -> dict[str, int]:
        import torch

        agents = list(observations)
        if "shared" in self.modules:
            groups = {"shared": agents}
        else:
            groups = {a: [a] for a in agents}
        actions = {}
        with torch.no_grad():
            for module_id, members in groups.items():
                obs = torch.from_numpy(np.stack([observations[a] for a in members]).astype(np.float32))
                logits = self.modules[module_id].forward_inference({"obs": obs})["action_dist_inputs"]
                for a, x in zip(members, logits.argmax(-1).tolist(), strict=True):
                    actions[a] = int(x)
        return actions

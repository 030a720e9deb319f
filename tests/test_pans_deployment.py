"""The all-PANS deployment: stock firmware everywhere, calibration by role switching.

The emulated anchors follow what the host scripts that survey stock-PANS anchors rely on
(``acts``/``acas`` store a role, ``nis`` the network, ``reset`` reboots into it in generic mode,
``si`` names the node); the test runs an episode of the env over pseudo-terminals with a
per-anchor round and a team round, and checks that no anchor is left in tag mode.
"""

import numpy as np
import pytest

import uwb_env
from uwb_env.config import EnvConfig
from uwb_env.hardware.backend import HardwareConfig, connect_pans
from uwb_env.hardware.emulator import Scene, emulated_anchor_ids, pans_setup
from uwb_env.localization import rigid_align

STATIC = {"anchor_motion": {"model": "static"}, "tag_motion": {"model": "static"}}


def test_all_pans_episode_with_per_anchor_and_team_rounds():
    cfg = EnvConfig.from_dict({"max_cycles": 50, "action_mode": "per_anchor", "sim": STATIC})
    scene = Scene(cfg.sim, seed=4)
    emu, urls = pans_setup(scene, boot_s=0.2)
    with emu:
        world = connect_pans(cfg.sim, [urls[f"anchor_{i}"] for i in range(4)], [urls[f"tag_{i}"] for i in range(3)],
                             hardware=HardwareConfig(pans_role_switch_s=1.5))
        assert world.anchor_ids == emulated_anchor_ids()  # read from the anchors themselves ('si')
        env = uwb_env.parallel_env(config=cfg, backend=world)
        obs, infos = env.reset(seed=0)  # the first calibration: every anchor surveyed in turn
        first = env.system.calibration_count
        t = failures = 0
        while env.agents:
            actions = {a: 0 for a in env.agents}
            if t == 2:
                actions["anchor_2"] = 1  # re-locate me
            if t == 15:
                actions["anchor_0"] = 2  # a team round
            obs, rewards, terms, truncs, infos = env.step(actions)
            failures += bool(infos and next(iter(infos.values()))["calibration_failed"])
            t += 1
        world.close()
        devices = [emu.devices[f"anchor_{i}"] for i in range(4)]
    assert first == 1 and failures == 0
    assert env.system.anchor_round_count >= 1  # anchor 2 re-located by its own role switch
    assert env.system.calibration_count >= 2  # the team round
    assert all(d.role == "anchor" for d in devices)  # nobody left in tag mode
    assert sum(d.role_switches for d in devices) >= 2 * (4 + 1 + 4)
    est, truth = env.system.world.anchors_est, scene.anchors_true()
    rot, trans = rigid_align(est, truth)
    assert np.linalg.norm(est @ rot.T + trans - truth, axis=1).max() < 0.15
    tags = env.system.tag_fix @ rot.T + trans
    assert np.linalg.norm(tags - scene.tags_true(), axis=1).max() < 0.3


def test_tiers_anchors_cannot_run_per_anchor_rounds():
    from uwb_env.hardware.backend import HardwareWorld
    from uwb_env.hardware.drivers import TiersAnchorDriver

    class _Port:
        url = "none://"

    sim = EnvConfig.from_dict({"sim": {**STATIC, "n_tags": 0}}).sim
    w = HardwareWorld(sim, TiersAnchorDriver(_Port()), [], anchor_ids=["1150", "1151", "1152", "1153"])
    with pytest.raises(ValueError, match="all-PANS"):
        w.start_calibration_round(initiators=[1])


def test_connect_pans_checks_the_port_count():
    sim = EnvConfig.from_dict({"sim": STATIC}).sim
    with pytest.raises(ValueError, match="anchor_urls"):
        connect_pans(sim, ["loop://"] * 3, [])

"""The default scenario keeps the formation a localization team is deployed in."""

import numpy as np

from uwb_env.config import MotionConfig, SimConfig
from uwb_env.sim import World


def _hull_contains(poly: np.ndarray, pts: np.ndarray) -> np.ndarray:
    # convex polygon, counter-clockwise or not: all cross products of one sign
    centre = poly.mean(0)
    order = np.argsort(np.arctan2(*(poly - centre).T[::-1]))
    p = poly[order]
    edges = np.roll(p, -1, axis=0) - p
    rel = pts[:, None, :] - p[None]
    cross = edges[None, :, 0] * rel[..., 1] - edges[None, :, 1] * rel[..., 0]
    return (cross >= -1e-9).all(1) | (cross <= 1e-9).all(1)


def test_default_anchors_patrol_their_slots_and_tags_stay_inside():
    cfg = SimConfig(n_tags=6)
    assert cfg.anchor_motion.model == "patrol" and cfg.tag_motion.model == "inside_hull"
    world = World(cfg)
    world.reset(np.random.default_rng(0))
    home = world.anchors_true.copy()
    max_dev, outside = 0.0, 0
    for _ in range(3000):  # 10 minutes
        world.step()
        max_dev = max(max_dev, float(np.linalg.norm(world.anchors_true - home, axis=1).max()))
        outside += int((~_hull_contains(home, world.tags_true)).sum())
    # a waypoint lies within the radius; the path to it plus the position noise a little beyond
    assert max_dev < cfg.anchor_motion.patrol_radius_m + 0.5
    assert outside == 0


def test_free_motion_stays_available():
    cfg = SimConfig(anchor_motion=MotionConfig(model="heading"), tag_motion=MotionConfig(model="heading"))
    world = World(cfg)
    world.reset(np.random.default_rng(0))
    home = world.anchors_true.copy()
    for _ in range(1500):
        world.step()
    assert np.linalg.norm(world.anchors_true - home, axis=1).max() > 3.0

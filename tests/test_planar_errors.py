"""The ground-truth error kernel shared by the single and the batched env, against an
independent computation (SVD Procrustes from ``rigid_align``)."""

import numpy as np

from uwb_env.localization import rigid_align
from uwb_env.sim.planar_errors import planar_errors


def test_planar_errors_match_an_svd_procrustes_reference(rng):
    b, n, m, cap = 6, 5, 4, 3.0
    angle = rng.uniform(-np.pi, np.pi, b)
    rot = np.stack([[[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]] for a in angle])
    origin = rng.uniform(-5, 5, (b, 2))
    anchors_true = rng.uniform(0, 20, (b, n, 2))
    tags_true = rng.uniform(0, 20, (b, m, 2))
    truth_a = np.einsum("bij,bnj->bni", rot, anchors_true - origin[:, None])
    truth_t = np.einsum("bij,bnj->bni", rot, tags_true - origin[:, None])
    # estimates: the truth turned and shifted (unobservable) plus errors
    turn = rng.uniform(-0.3, 0.3, b)
    q = np.stack([[[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]] for a in turn])
    anchors_est = np.einsum("bij,bnj->bni", q, truth_a) + 1.0 + rng.normal(0, 0.2, (b, n, 2))
    tag_fix = np.einsum("bij,bnj->bni", q, truth_t) + 1.0 + rng.normal(0, 1.5, (b, m, 2))
    tag_fix[0, 1] = np.nan  # no fix: counts as the cap
    a_const, t_const, a_fixed, t_fixed, rotation = planar_errors(rot, origin, anchors_true, tags_true, anchors_est,
                                                                 tag_fix, cap)
    for k in range(b):
        r, t = rigid_align(truth_a[k], anchors_est[k], allow_reflection=False)
        np.testing.assert_allclose(a_const[k], np.linalg.norm(anchors_est[k] - (truth_a[k] @ r.T + t), axis=1),
                                   rtol=1e-9, atol=1e-12)
        want_t = np.linalg.norm(tag_fix[k] - (truth_t[k] @ r.T + t), axis=1)
        np.testing.assert_allclose(t_const[k], np.minimum(np.where(np.isfinite(want_t), want_t, cap), cap),
                                   rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(a_fixed[k], np.linalg.norm(anchors_est[k] - truth_a[k], axis=1), rtol=1e-9)
        want_f = np.linalg.norm(tag_fix[k] - truth_t[k], axis=1)
        np.testing.assert_allclose(t_fixed[k], np.minimum(np.where(np.isfinite(want_f), want_f, cap), cap), rtol=1e-9)
        d_true, d_est = truth_a[k, 1] - truth_a[k, 0], anchors_est[k, 1] - anchors_est[k, 0]
        cos = d_true @ d_est / np.linalg.norm(d_true) / np.linalg.norm(d_est)
        np.testing.assert_allclose(rotation[k], np.arccos(np.clip(cos, -1, 1)), atol=1e-9)
    assert t_const[0, 1] == cap and np.all(t_const <= cap)
    # the batched env's call (constellation errors only) gives the same numbers
    only = planar_errors(rot, origin, anchors_true, tags_true, anchors_est, tag_fix, cap, False)
    np.testing.assert_array_equal(only[0], a_const)
    np.testing.assert_array_equal(only[1], t_const)
    assert only[2].size == only[3].size == only[4].size == 0

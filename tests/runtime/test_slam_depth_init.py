"""Factored-sampling depth initialisation on a synthetic camera translating sideways."""

import numpy as np

from runtime.slam.depth_init import DepthParticles, step


def test_particles_converge_on_the_true_depth_and_pass_the_gaussian_test():
    f, c = 500.0, np.array([320.0, 240.0])
    true = np.array([0.2, -0.1, 2.3])                 # a point 2.3 m ahead of the first camera
    d = true / np.linalg.norm(true)
    p = DepthParticles.create(np.zeros(3), d, np.zeros((15, 15)), c + f * true[:2] / true[2])
    rng = np.random.default_rng(0)
    for k in range(1, 30):
        cam = np.array([0.01 * k, 0.0, 0.0])           # 1 cm per frame sideways: parallax grows
        sigma_cam = 0.005                              # camera position uncertainty, m

        def project(P):
            X = P - cam
            uv = c + f * X[:, :2] / X[:, 2:3]
            # Pixel noise plus the camera's uncertainty seen at each particle's depth.
            s2 = 1.0 + (f * sigma_cam / X[:, 2]) ** 2
            return uv, s2[:, None, None] * np.eye(2)

        def match(uv, S):
            X = true - cam
            return c + f * X[:2] / X[2] + rng.normal(0, 1.0, 2), 400.0

        step(p, project, match)
        if p.is_gaussian():
            break
    assert p.is_gaussian(), (p.mean, p.std)
    assert abs(p.mean - np.linalg.norm(true)) < 3 * p.std + 0.05
    assert len(p.depths) < 100                         # weak particles were pruned


def test_a_failed_search_is_counted_and_changes_nothing():
    p = DepthParticles.create(np.zeros(3), np.array([0, 0, 1.0]), np.zeros((15, 15)), np.array([320, 240.0]))
    w = p.weights.copy()
    step(p, lambda P: (np.zeros((len(P), 2)), np.tile(np.eye(2), (len(P), 1, 1))), lambda uv, S: None)
    assert p.failures == 1 and np.array_equal(w, p.weights)


def test_one_wrong_match_does_not_prune_the_true_depth_when_outliers_are_modelled():
    f, c = 500.0, np.array([320.0, 240.0])
    d = np.array([0.0, 0.0, 1.0])
    cam = np.array([0.05, 0.0, 0.0])                   # 5 cm baseline: depths spread over ~45 px

    def project(P):
        X = P - cam
        return c + f * X[:, :2] / X[:, 2:3], np.tile(np.eye(2), (len(P), 1, 1))

    true_depth = 2.0
    z_true = c + f * (true_depth * d - cam)[:2] / true_depth
    z_wrong = z_true + np.array([-20.0, 0.0])          # another corner on the epipolar band
    for outlier, survives in ((0.0, False), (0.1, True)):
        p = DepthParticles.create(np.zeros(3), d, np.zeros((15, 15)), c)
        step(p, project, lambda uv, S: (z_wrong, 60.0 * 8.0), prune=0.001, outlier=outlier)
        assert (np.abs(p.depths - true_depth).min() < 0.05) == survives, (outlier, p.depths)
        if survives:
            for _ in range(3):                         # the true match then wins it back
                step(p, project, lambda uv, S: (z_true, 60.0 * 8.0), prune=0.001, outlier=outlier)
            assert abs(p.mean - true_depth) < 0.1, p.mean

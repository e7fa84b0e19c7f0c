"""Metric functions of dqm.evaluation on hand-made cases with answers worked out by hand."""
import numpy as np
import pytest

from dqm import evaluation as E


def test_cluster_pairs_drops_same_image_pairs():
    labels = np.array([0, 0, 1, 0, 1])
    ids = np.array([0, 1, 0, 0, 1])
    a, b = E.cluster_pairs(labels, ids)
    assert sorted(zip(a.tolist(), b.tolist())) == [(0, 1), (1, 3), (2, 4)]


def test_cluster_pairs_of_singletons_is_empty():
    a, b = E.cluster_pairs(np.arange(4), np.array([0, 1, 2, 3]))
    assert len(a) == len(b) == 0


def test_landmark_scores_by_hand():
    # image 0: points 0, 1, unknown; image 1: points 0, 1; image 2: point 0
    pid = np.array([0, 1, -1, 0, 1, 0])
    ids = np.array([0, 0, 0, 1, 1, 2])
    # truth: point 0 seen in 3 images -> 3 pairs, point 1 in 2 -> 1 pair
    s = E.landmark_scores(np.array([0, 2]), np.array([3, 4]), pid, ids)
    assert (s.n_predicted, s.n_correct, s.n_truth) == (2, 1, 4)
    assert s.precision == pytest.approx(0.5) and s.recall == pytest.approx(0.25)
    assert s.f1 == pytest.approx(2 * 0.5 * 0.25 / 0.75)


def _translation_scene():
    # image 0 -> image 1 is a shift by +10 px in x
    xy = np.array([[0, 0], [50, 50], [100, 100],  # image 0: f0, f1, f2
                   [10, 0], [60, 50], [61, 50], [300, 300]], float)  # image 1: f3..f6
    ids = np.array([0, 0, 0, 1, 1, 1, 1])
    T = np.array([[1, 0, 10], [0, 1, 0], [0, 0, 1]], float)

    def H(i, j):
        return T if (i, j) == (0, 1) else np.linalg.inv(T)
    return xy, ids, H


def test_homography_scores_by_hand():
    xy, ids, H = _translation_scene()
    # one-to-one truth: f0-f3, f1-f4 (f5 is 1 px off f1's projection but f1 is taken); f2 has none
    truth = E.HomographyTruth(xy, ids, H, tol=5.0)
    assert truth.n_truth == 2
    # (0,3) correct and in the truth; (5,1) correct (1 px), not in the one-to-one truth, given
    # in reversed orientation; (2,6) wrong
    s = truth.score(np.array([0, 5, 2]), np.array([3, 1, 6]))
    assert (s.n_predicted, s.n_correct, s.n_truth) == (3, 2, 2)
    assert s.precision == pytest.approx(2 / 3)
    assert s.recall == pytest.approx(1 / 2)  # only f0-f3 counts for recall
    assert s.f1 == pytest.approx(4 / 7)
    good, in_truth = truth.correct(np.array([0, 5, 2]), np.array([3, 1, 6]))
    assert good.tolist() == [True, True, False] and in_truth.tolist() == [True, False, False]
    # the functional form gives the same numbers
    assert E.homography_scores(np.array([0, 5, 2]), np.array([3, 1, 6]), xy, ids, H, tol=5.0) == s


def test_homography_tolerance_is_inclusive_and_respected():
    xy, ids, H = _translation_scene()
    assert E.HomographyTruth(xy, ids, H, tol=1.0).score(np.array([1]), np.array([5])).n_correct == 1
    assert E.HomographyTruth(xy, ids, H, tol=0.5).score(np.array([1]), np.array([5])).n_correct == 0


def test_scores_of_no_prediction():
    xy, ids, H = _translation_scene()
    s = E.HomographyTruth(xy, ids, H).score(np.zeros(0, int), np.zeros(0, int))
    assert s.precision == 1.0 and s.recall == 0.0 and s.f1 == 0.0


def test_violations_of_a_partition_are_zero():
    ids = np.array([0, 1, 2])
    v = E.consistency_violations(np.array([0, 1, 0]), np.array([1, 2, 2]), ids)
    assert (v.n_matches, v.n_tracks, v.c1_features, v.c1_pairs, v.c2_tracks, v.c2_features) == (3, 1, 0, 0, 0, 0)


def test_violations_c1_non_transitive():
    # 0-1 and 1-2 matched (three images) but 0-2 not: C1 broken for features 0 and 2
    v = E.consistency_violations(np.array([0, 1]), np.array([1, 2]), np.array([0, 1, 2]))
    assert (v.c1_features, v.c1_pairs, v.c2_tracks, v.c2_features) == (2, 1, 0, 0)


def test_violations_c2_two_features_of_one_image():
    # features 0 and 2 are both in image 0 and end up in one track through feature 1
    v = E.consistency_violations(np.array([0, 1]), np.array([1, 2]), np.array([0, 1, 0]))
    assert (v.c2_tracks, v.c2_features, v.c1_features) == (1, 2, 0)


def test_violations_ignore_duplicates_self_and_same_image_pairs():
    v = E.consistency_violations(np.array([0, 1, 0, 0]), np.array([1, 0, 0, 2]), np.array([0, 1, 0]))
    assert v.n_matches == 1 and v.c2_tracks == 0


def test_violations_reject_bad_indices():
    with pytest.raises(ValueError, match="0..2"):
        E.consistency_violations(np.array([0]), np.array([3]), np.array([0, 1, 2]))


def test_pr_auc_by_hand():
    # points (R, P) = (0.5, 1.0), (1.0, 0.5); extended flat to recall 0
    assert E.pr_auc([0.5, 1.0], [1.0, 0.5]) == pytest.approx(0.5 + 0.5 * 0.75)
    assert E.pr_auc([1.0, 0.5], [0.5, 1.0]) == pytest.approx(0.875)  # order does not matter
    assert E.pr_auc([0.4], [0.5]) == pytest.approx(0.2)
    assert E.pr_auc([], []) == 0.0
    with pytest.raises(ValueError):
        E.pr_auc([0.5, 1.2], [1.0, 0.5])
    with pytest.raises(ValueError):
        E.pr_auc([0.5], [1.0, 0.5])


def test_pr_curve_round_trip_and_f1():
    c = E.PRCurve("m", "rho", np.array([0.5, 1.0]), np.array([1.0, 0.5]), np.array([0.5, 1.0]))
    assert c.auc() == pytest.approx(0.875)
    np.testing.assert_allclose(c.f1, [2 / 3, 2 / 3])
    d = E.PRCurve.from_dict(c.as_dict())
    np.testing.assert_array_equal(d.recall, c.recall)
    assert d.auc() == c.auc()


def test_chance_truth_pairs_and_the_bounds_on_the_real_ones():
    """Keypoints scattered at random with no correspondence: the one-to-one truth within 5 px still pairs many,
    and chance_truth_pairs (the truth under shifted homographies) counts about as many; the same keypoints with
    a copy of a third of them in the other image (real correspondences, 0.5 px of noise): real_truth_pairs'
    bounds hold the 1,000 real ones, and a truth of nothing but chance gets a lower bound near 0."""
    rng = np.random.default_rng(0)
    xa = rng.uniform(0, 800, (3000, 2))
    xb = rng.uniform(0, 800, (3000, 2))
    H = np.eye(3)
    truth = len(E.one_to_one_truth(H, xa, xb, 5.0)[0])
    chance = E.chance_truth_pairs(H, xa, xb, 5.0)
    assert truth > 300 and abs(chance - truth) < 0.15 * truth
    assert E.real_truth_pairs(truth, chance, 3000, 3000)[0] < 0.15 * truth
    real = np.r_[xa[:1000] + rng.normal(0, 0.5, (1000, 2)), xb[1000:]]
    truth = len(E.one_to_one_truth(H, xa, real, 5.0)[0])
    chance = E.chance_truth_pairs(H, xa, real, 5.0)
    lo, hi = E.real_truth_pairs(truth, chance, 3000, 3000)
    assert lo < 1000 < hi < truth and hi - lo < 0.5 * 1000
    assert E.chance_truth_pairs(H, xa, real, 5.0, shifts=[(0.0, 0.0)]) == truth

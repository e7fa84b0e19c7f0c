"""QuickMatch on real data with ground truth (skipped when ../shared is absent)."""
from conftest import assert_consistent, require_data

import dqm
from dqm import evaluation
from dqm.vision import datasets, features


def test_cmu_hotel_landmarks_at_default_rho():
    seq = datasets.load_landmark_sequence(require_data("cmu_hotel"))
    D, ids, landmark, _ = features.landmark_descriptors(seq)
    assert D.shape == (3030, 128)
    r = dqm.quickmatch(D, ids)
    assert_consistent(r.labels, ids)
    s = evaluation.cluster_scores_landmarks(r.labels, landmark, ids)
    assert s.precision >= 0.99, s
    assert s.recall >= 0.85, s

"""Online QuickMatch: labels identical to batch after every add and remove; events replay; stable ids."""
import warnings

import numpy as np
import pytest
from conftest import assert_consistent, require_data

import dqm
from dqm import synthetic
from dqm.core.events import replay
from dqm.vision import datasets, features


def batch_labels(om: dqm.OnlineQuickMatch) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # one image left: batch warns that nothing can match
        return dqm.quickmatch(om.descriptors, om.image_ids, rho=om.rho, kernel="quadratic",
                              parent=om.parent_mode).labels


def follow(om, X, img_ids, order, rng=None, remove_rate=0.0, window=None):
    """Add the images in ``order`` one at a time (removing some, or keeping a window) and check,
    after every call, labels against batch and the replayed events against the new assignment."""
    assign = {}
    calls = 0

    def check(cs):
        nonlocal calls
        calls += 1
        before = dict(assign)
        replay(assign, cs.events)
        assert assign == om.assignment()
        # clusters untouched by any event keep their ids
        moved = {int(k) for e in cs.events for k in e.features}
        for k, c in om.assignment().items():
            if k in before and k not in moved:
                assert before[k] == c
        ref = batch_labels(om)
        assert np.array_equal(om.labels, ref)
        if len(ref):
            assert_consistent(om.labels, om.image_ids)

    for img in order:
        m = img_ids == img
        if window is not None and len(om.images) >= window:
            check(om.remove(int(om.images[0])))
        check(om.add(X[m], img_ids[m]))
        if rng is not None and rng.random() < remove_rate and len(om.images) > 1:
            check(om.remove(int(rng.choice(om.images))))
    return calls


def mixed_data(rng, integer: bool):
    """Small random sets with single-feature images, in-image duplicates (sigma 0) and cross-image twins."""
    sizes = rng.integers(1, 14, size=11)
    sizes[rng.integers(11, size=2)] = 1
    base = rng.normal(size=(18, 8))
    X, img_ids = [], []
    for i, sz in enumerate(sizes):
        pts = base[rng.integers(18, size=sz)] + rng.normal(scale=0.3, size=(sz, 8))
        if integer:
            pts = np.round(pts * 3)
        if sz > 3 and rng.random() < 0.5:
            pts[1] = pts[0]
        X.append(pts)
        img_ids.append(np.full(sz, 7 * i + 3))
    return np.vstack(X), np.concatenate(img_ids)


@pytest.mark.parametrize("rho", [0.7, 1.0, 1.5])
@pytest.mark.parametrize("parent", ["any", "other-image"])
def test_random_data_with_removals_matches_batch_after_every_call(rho, parent):
    for trial in range(3):
        rng = np.random.default_rng(trial)
        X, img_ids = mixed_data(rng, integer=trial % 2 == 0)
        om = dqm.OnlineQuickMatch(rho=rho, parent=parent)
        order = rng.permutation(np.unique(img_ids))
        assert follow(om, X, img_ids, order, rng=rng, remove_rate=0.5) >= len(order)


def test_synthetic_sift_one_image_at_a_time_matches_batch():
    s = synthetic.sift_like(n_images=14, n_points=150, clutter_per_image=40, seed=3)
    om = dqm.OnlineQuickMatch(rho=0.9)
    follow(om, s.descriptors, s.image_ids, np.unique(s.image_ids))
    assert om.n_features == len(s.descriptors)


def test_synthetic_sift_sliding_window_and_several_images_per_add():
    s = synthetic.sift_like(n_images=12, n_points=120, clutter_per_image=30, seed=4)
    X, img_ids = s.descriptors, s.image_ids
    om = dqm.OnlineQuickMatch(rho=0.9)
    follow(om, X, img_ids, np.unique(img_ids), window=4)
    assert len(om.images) == 4
    # several images in one call, then removals down to nothing
    om = dqm.OnlineQuickMatch(rho=0.9)
    m = img_ids < 5
    cs = om.add(X[m], img_ids[m])
    assert np.array_equal(om.labels, batch_labels(om))
    assert {e.kind for e in cs.events} == {"created"}
    for img in list(om.images):
        om.remove(img)
        assert np.array_equal(om.labels, batch_labels(om))
    assert om.n_features == 0 and len(om.labels) == 0


def test_events_name_what_happened():
    s = synthetic.sift_like(n_images=6, n_points=120, clutter_per_image=20, seed=5)
    X, img_ids = s.descriptors, s.image_ids
    om = dqm.OnlineQuickMatch(rho=0.9)
    for img in range(5):
        om.add(X[img_ids == img], img_ids[img_ids == img])
    before = om.assignment()
    cs = om.add(X[img_ids == 5], img_ids[img_ids == 5])
    kinds = cs.counts()
    assert kinds["grown"] > 0 and kinds["created"] > 0
    for e in cs.events:
        if e.kind == "grown" and not e.new:
            assert e.cluster in before.values()       # an existing track gained features of image 5
            assert set(e.images.tolist()) == {5}
        if e.kind == "created":
            assert e.cluster not in before.values() and set(e.images.tolist()) == {5}
    assert sorted(cs.added.tolist()) == sorted(k for k in om.keys.tolist() if k not in before)
    # removing the image again: exactly its features leave (shrunk / removed), in events naming image 5
    assign = om.assignment()
    cs = om.remove(5)
    left = np.concatenate([e.features for e in cs.events if e.kind in ("shrunk", "removed")])
    assert sorted(left.tolist()) == sorted(cs.removed.tolist())
    assert all(set(e.images.tolist()) == {5} for e in cs.events if e.kind in ("shrunk", "removed"))
    assert replay(assign, cs.events) == om.assignment()
    assert str(cs.events[0]) and cs.summary().startswith("+0 / -")


def test_hotel_landmarks_frame_by_frame_matches_batch():
    seq = datasets.load_landmark_sequence(require_data("cmu_hotel"))
    D, ids, _, _ = features.landmark_descriptors(seq)
    om = dqm.OnlineQuickMatch(rho=0.9)
    # the first 60 frames (of 101), checked against batch after every add and remove (all 101 frames, as
    # SIFT: scripts/bench_online.py --sequences hotel)
    follow(om, D, ids, np.unique(ids)[:60], rng=np.random.default_rng(0), remove_rate=0.1)


def test_hotel_sift_frames_sliding_window_matches_batch():
    seq = datasets.load_landmark_sequence(require_data("cmu_hotel"))
    D, ids, _ = features.extract_many(seq.image_paths[:12], max_features=250)
    om = dqm.OnlineQuickMatch(rho=0.9)
    follow(om, D, ids, np.unique(ids), window=6)


def test_bad_input_is_refused_before_any_change():
    s = synthetic.sift_like(n_images=3, n_points=40, clutter_per_image=5, seed=6)
    X, img_ids = s.descriptors, s.image_ids
    with pytest.raises(dqm.InputError, match="finite kernel"):
        dqm.OnlineQuickMatch(kernel="gaussian")
    with pytest.raises(dqm.InputError, match="rho"):
        dqm.OnlineQuickMatch(rho=-1)
    om = dqm.OnlineQuickMatch()
    om.add(X[img_ids == 0], img_ids[img_ids == 0])
    state = (om.assignment(), om.labels.copy())
    bad = X[img_ids == 1].astype(float)
    bad[3, 5] = np.nan
    with pytest.raises(dqm.InputError, match="NaN"):
        om.add(bad, img_ids[img_ids == 1])
    with pytest.raises(dqm.InputError, match="already present"):
        om.add(X[img_ids == 0], img_ids[img_ids == 0])
    with pytest.raises(dqm.InputError, match="dimensions"):
        om.add(X[img_ids == 1][:, :64], img_ids[img_ids == 1])
    with pytest.raises(dqm.InputError, match="not present"):
        om.remove(9)
    assert (om.assignment(), om.labels.tolist()) == (state[0], state[1].tolist())
    cs = om.add(np.zeros((0, 128)), np.zeros(0, int))  # a frame without features changes nothing
    assert cs.events == [] and om.assignment() == state[0]
    om.add(X[img_ids == 1], img_ids[img_ids == 1])
    assert np.array_equal(om.labels, batch_labels(om))


def test_bench_online_quick_runs_and_checks_every_step(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "scripts" / "bench_online.py"
    p = subprocess.run([sys.executable, str(script), "--quick", "--out-dir", str(tmp_path)],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "labels identical to batch at every checked step: True (20 of 20 steps)" in p.stdout
    out = json.loads((tmp_path / "bench_online.json").read_text())["results"]["generated"]
    assert out["identical_every_checked_step"] and out["steps_checked"] == 20
    assert (tmp_path / "bench_online.png").stat().st_size > 0

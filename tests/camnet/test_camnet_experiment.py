"""The camera-network simulator, pipeline and whole experiment at a small size."""
import json
import math

import numpy as np
import pytest

from dqm import InputError
from dqm.camnet.experiment import (
    calibrate,
    common_errors,
    detection_curve,
    localization_errors,
    operating_point,
    run_experiment,
)
from dqm.camnet.geometry import Camera
from dqm.camnet.pipeline import METHODS, PipelineConfig, detect, match_all, pairwise_pair_candidates, quickmatch_matches
from dqm.camnet.simulator import BoxObject, SimConfig, build_world
from dqm.cli import main
from dqm.core import quickmatch
from dqm.vision.features import extract

#: the small experiment: the default 30 s loop of seed 0 sampled every 3 s (10 steps x 5 cameras)
SMALL = dict(seed=0, duration=30.0, rate=1.0 / 3.0)


@pytest.fixture(scope="module")
def world():
    return build_world(**SMALL)


@pytest.fixture(scope="module")
def small_run():
    return run_experiment(SimConfig(**SMALL), PipelineConfig())


# --- simulator -------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs,match", [
    (dict(n_cameras=0), "n_cameras"),
    (dict(duration=-1), "duration"),
    (dict(rate=0.01, duration=10), "no time step"),
    (dict(hfov=200), "hfov"),
    (dict(arena=(2, 2)), "arena"),
    (dict(noise=-1), "noise"),
    (dict(jpeg_quality=0), "jpeg_quality"),
    (dict(image_size=(10, 10)), "image_size"),
    (dict(target_size=(3, 3, 1)), "too large"),
])
def test_sim_config_rejects_bad_values(kwargs, match):
    with pytest.raises(InputError, match=match):
        SimConfig(**kwargs)


def test_world_is_deterministic_and_seeded(world):
    again = build_world(**SMALL)
    a, ta = world.render(2, 3)
    b, tb = again.render(2, 3)
    assert a.dtype == np.uint8 and a.shape == (480, 640)
    assert np.array_equal(a, b) and np.array_equal(ta.visible_px, tb.visible_px)
    # frames do not depend on rendering order
    world.render(0, 0)
    assert np.array_equal(world.render(2, 3)[0], a)
    other = build_world(seed=1, duration=30.0, rate=1.0 / 3.0)
    assert not np.array_equal(other.render(2, 3)[0], a)
    assert world.n_steps == 10 and len(world.cameras) == 5 and len(world.references) == 4
    with pytest.raises(InputError, match="camera"):
        world.render(5, 0)
    with pytest.raises(InputError, match="time step"):
        world.render(0, 10)


def test_target_enters_and_leaves_views(world):
    vis = np.zeros((world.n_steps, 5), bool)
    border = 0
    for k in range(world.n_steps):
        for c in range(5):
            _, t = world.render(c, k, clean=True)
            vis[k, c] = t.visible
            assert t.position == pytest.approx(world.target_centre(k)[:2])
            if t.box is not None and (t.box[0] < 0 or t.box[2] > 639):
                border += 1
    assert vis.any(axis=0).sum() >= 4 and (~vis).any(axis=0).sum() >= 4  # cameras gain and lose the target
    assert 0.2 < vis.mean() < 0.8
    assert border >= 2  # the image border cuts the target in some frames


def test_rendered_target_box_matches_projection(world):
    """A clean render of the target alone: its box in the id buffer = its projected side, depth exact."""
    cfg = world.config
    cam = Camera("t", np.array([0.0, 0.0, cfg.camera_height]), 0.0, 0.0, world.intrinsics)
    d = 2.5
    target = BoxObject("target", (d + cfg.target_size[1] / 2, 0.0), math.pi, cfg.target_size, cfg.target_elevation,
                       ("target0", "target1", "target2", "target3"), cfg.target_px_per_m)
    img, tr = world.render_view(cam, target, np.random.default_rng(0), clean=True, static=False)
    side = [s for s in target.surfaces(0, "target", faces=True) if s.face == 0][0]
    uv, _ = cam.project(side.corners)
    assert tr.visible_px[0] > 0 and tr.visible_px[1:].sum() == 0  # only the front side faces the camera
    assert tr.box == pytest.approx((uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()), abs=1.0)
    assert tr.depth == pytest.approx(d + cfg.target_size[1] / 2)
    assert tr.bearing == pytest.approx(0.0, abs=1e-9)


def test_pipeline_localizes_rendered_target(world):
    """Render the target at a known pose, detect it with the pipeline: distance and bearing within tolerance."""
    cfg = world.config
    pipe = PipelineConfig()
    refs = [extract(r, "paper") for r in world.references]
    calib = calibrate(world, refs, pipe)
    assert calib.range_constant == pytest.approx(calib.ideal, rel=0.03)
    cam = Camera("t", np.array([0.5, -0.3, cfg.camera_height]), math.radians(20), 0.0, world.intrinsics)
    depth_face, bearing = 3.0, math.radians(12)
    f = np.array([math.cos(cam.yaw), math.sin(cam.yaw)])
    r = np.array([math.sin(cam.yaw), -math.cos(cam.yaw)])
    face_centre = cam.position[:2] + depth_face * f + depth_face * math.tan(bearing) * r
    centre = face_centre + f * cfg.target_size[1] / 2  # the box extends away from the camera
    target = BoxObject("target", tuple(centre), cam.yaw + math.pi, cfg.target_size, cfg.target_elevation,
                       ("target0", "target1", "target2", "target3"), cfg.target_px_per_m)
    img, tr = world.render_view(cam, target, np.random.default_rng(0), clean=True, static=False)
    feats = extract(img, "paper")
    matches = [pairwise_pair_candidates(ref, feats, "bf").select(0.75) for ref in refs]
    sizes = [(r.shape[1], r.shape[0]) for r in world.references]
    det = detect("bf", 0, 0, matches, refs, sizes, feats, cam, calib.range_constant, [cfg.target_size[1] / 2] * 4,
                 pipe)
    assert det.reference == 0 and det.score >= 10 and det.box is not None
    est = np.array(det.estimate)
    assert np.linalg.norm(est - centre) < 0.1
    dist_true = np.linalg.norm(centre - cam.position[:2])
    assert np.linalg.norm(est - cam.position[:2]) == pytest.approx(dist_true, rel=0.03)
    b_est = math.atan2(*(est - cam.position[:2])[::-1]) - cam.yaw
    assert abs(math.degrees(-b_est) - math.degrees(math.atan2(depth_face * math.tan(bearing), dist_true))) < 1.5


def test_quickmatch_matches_are_co_clustered_pairs(world):
    refs = [extract(r, "paper") for r in world.references]
    cams = [extract(world.render(c, 0)[0], "paper") for c in range(2)]
    matches, labels = quickmatch_matches(refs, cams, 0.75)
    offsets = np.r_[0, np.cumsum([len(f) for f in refs + cams])]
    for c in range(2):
        for r in range(4):
            a, b = matches[c][r]
            assert np.array_equal(labels[offsets[r] + a], labels[offsets[4 + c] + b])
    with pytest.raises(InputError, match="labels"):
        quickmatch_matches(refs, cams, 0.75, labels=labels[:-1])


def _same_matches(a, b):
    assert len(a) == len(b)
    for (ra, ca), (rb, cb) in zip(a, b):
        assert np.array_equal(ra, rb) and np.array_equal(ca, cb)


def test_online_matcher_equals_batch_quadratic(world):
    """Online clusters = batch quadratic QuickMatch over the same features in arrival order (mid-step, step end)."""
    from dqm.camnet.online import OnlineMatcher

    refs = [extract(r, "paper") for r in world.references]
    frames = {(t, c): extract(world.render(c, t)[0], "paper") for t in (0, 1) for c in range(3)}
    on = OnlineMatcher(refs, 3, 0.75)
    for c in range(3):
        on.update(0, c, frames[(0, c)])
    row = on.update(1, 0, frames[(1, 0)])  # camera 0 replaced its frame; cameras 1, 2 still hold step 0
    cams = [frames[(0, 1)], frames[(0, 2)], frames[(1, 0)]]  # arrival order
    batch, labels = quickmatch_matches(refs, cams, 0.75, kernel="quadratic")
    assert np.array_equal(on.om.labels, labels)
    _same_matches(row, batch[2])
    assert sum(len(m[0]) for m in row) > 0
    for c in (1, 2):
        on.update(1, c, frames[(1, c)])
    # every camera now holds its step-1 frame: the batch input of step 1, in the batch order
    cams = [frames[(1, c)] for c in range(3)]
    batch, labels = quickmatch_matches(refs, cams, 0.75, kernel="quadratic")
    D = np.vstack([f.descriptors for f in refs + cams])
    assert np.array_equal(on.om.descriptors, D)
    assert np.array_equal(labels, quickmatch(D, np.concatenate([np.full(len(f), k) for k, f in
                                                                enumerate(refs + cams)]),
                                             rho=0.75, kernel="quadratic").labels)
    assert np.array_equal(on.om.labels, labels)
    for c in range(3):
        _same_matches(on.matches(c), batch[c])
    assert on.om.n_features == len(D) and on.current_images() == [4 + 3 + c for c in range(3)]
    st = on.stats()
    assert st["frames"] == 6 and st["update_mean_s"] > 0 and st["features_max"] == max(on.set_sizes)
    with pytest.raises(InputError, match="time order"):
        on.update(1, 0, frames[(1, 0)])
    with pytest.raises(InputError, match="one frame at a time"):
        match_all("quickmatch-online", refs, cams, PipelineConfig())


# --- the whole experiment ------------------------------------------------------------------------
def test_small_experiment_quickmatch_detects_best(small_run):
    res = small_run
    assert res.n_frames == 50 and 10 < res.n_positive < 40
    auc = {m: detection_curve(res, m).auc() for m in res.methods}
    assert auc["quickmatch"] >= auc["bf"], auc
    assert auc["quickmatch"] >= auc["flann"], auc
    for m in res.methods:
        curve = detection_curve(res, m)
        assert curve.recall[0] == 1.0  # threshold 0: every frame
        assert np.all(np.diff(curve.recall) <= 1e-12)
        op = operating_point(res, m)
        assert op["min_matches"] == 10 and op["detections"] >= 3
        err = localization_errors(res, m)
        assert len(err.errors) >= 3 and np.isfinite(err.errors).all()
        assert err.median < 0.5  # metres, in an 8 x 6 m arena
    common = common_errors(res)
    assert len({e.n_detections for e in common.values()}) == 1


def test_small_experiment_online_variant(small_run):
    """The online variant is run frame by frame; the last camera of each step sees the batch set."""
    res = small_run
    assert res.methods == METHODS
    on, ba = res.arrays("quickmatch-online"), res.arrays("quickmatch-quadratic")
    assert np.array_equal(on["step"], ba["step"]) and np.array_equal(on["camera"], ba["camera"])
    last = on["camera"] == 4
    assert np.array_equal(on["score"][last], ba["score"][last])
    assert np.array_equal(on["estimate"][last], ba["estimate"][last], equal_nan=True)
    assert detection_curve(res, "quickmatch-online").auc() > 0.5
    assert res.online["frames"] == 50 and res.online["update_mean_s"] > 0
    assert res.online["features_mean"] > res.n_features["per_reference_mean"] * 4
    assert "quickmatch-online" not in res.sweeps


def test_small_experiment_report(small_run, tmp_path):
    from dqm.camnet.report import seed_row, write_report

    written = write_report(small_run, tmp_path, command="test", seed_rows=[seed_row(small_run)])
    for name in ("pr", "trajectories", "errors", "views", "discovery", "clusters", "json", "markdown"):
        assert written[name].exists() and written[name].stat().st_size > 0, name
    data = json.loads(written["json"].read_text())
    assert set(data["methods"]) == set(METHODS)
    assert data["methods"]["quickmatch"]["paper"]["auc"] == 0.64
    assert data["methods"]["quickmatch-online"]["paper"] is None
    assert data["methods"]["quickmatch-online"]["kernel"] == "quadratic"
    vs = data["online"]["vs_batch_quadratic"]
    assert vs["same_score_last_camera"] == vs["last_camera_frames"] == 10
    assert data["online"]["update_mean_s"] > 0 and set(data["online"]["batch_per_step_s"]) == {
        "quickmatch", "quickmatch-quadratic"}
    md = written["markdown"].read_text()
    assert "Comparison with the paper" in md and "0.64" in md and "img/camnet_pr.png" in md
    assert "## Online QuickMatch" in md and "ms per frame" in md
    auc = data["methods"]["quickmatch-online"]["pr_auc"]
    assert f"| QuickMatch online, quadratic (rho 0.75) | **{auc:.3f}** |" in md
    assert "| QuickMatch quadratic kernel (rho 0.75) |" in md


def test_experiment_rejects_bad_input():
    with pytest.raises(InputError, match="method"):
        run_experiment(SimConfig(**SMALL), methods=("sift",))
    with pytest.raises(InputError, match="SimConfig"):
        run_experiment({"seed": 0})
    with pytest.raises(InputError, match="no methods"):
        run_experiment(SimConfig(**SMALL), methods=())
    with pytest.raises(InputError, match="min_matches"):
        PipelineConfig(min_matches=2)
    with pytest.raises(InputError, match="rho"):
        PipelineConfig(rho=0)
    with pytest.raises(InputError, match="preset"):
        PipelineConfig(preset="fast")


def test_cli_experiment(tmp_path, capsys):
    out = tmp_path / "out"
    # tiny, with the parameter sweep and a second seed: every section of the report
    rc = main(["experiment", "localization", "--cameras", "2", "--duration", "6", "--rate", "0.34",
               "--seeds", "3,4", "--rhos", "0.75,1.1", "--ratios", "0.7", "--out-dir", str(out), "--quiet"])
    assert rc == 0
    assert (out / "img" / "camnet_pr.png").exists() and (out / "img" / "camnet_pr_parameter.png").exists()
    md = (out / "camnet.md").read_text()
    for section in ("## Results", "## Online QuickMatch", "## The matching parameter", "## Comparison with the paper",
                    "## Other seeds", "QuickMatch per camera", "QuickMatch online PR AUC"):
        assert section in md, section
    data = json.loads((out / "camnet.json").read_text())
    assert [r["seed"] for r in data["seeds"]] == [3, 4]
    assert [r["ratio"] for r in data["methods"]["bf"]["sweep"]["table"]] == [0.7, 0.75]
    # a subset of the methods, online without batch QuickMatch
    rc = main(["experiment", "localization", "--cameras", "2", "--duration", "6", "--rate", "0.34", "--no-sweep",
               "--methods", "bf,quickmatch-online", "--out-dir", str(out / "sub"), "--quiet"])
    assert rc == 0
    data = json.loads((out / "sub" / "camnet.json").read_text())
    assert list(data["methods"]) == ["bf", "quickmatch-online"] and "vs_batch_quadratic" not in data["online"]
    assert "## Online QuickMatch" in (out / "sub" / "camnet.md").read_text()
    for argv, msg in ((["--seeds", "a,b"], "--seeds"), (["--cameras", "0"], "n_cameras"),
                      (["--rho", "-1"], "rho"), (["--seeds", "1,1"], "repeat"), (["--methods", "sift"], "sift"),
                      (["--methods", "bf,bf"], "at most once")):
        rc = main(["experiment", "localization", "--quick", "--out-dir", str(tmp_path / "bad"), "--quiet"] + argv)
        assert rc == 2
        assert msg in capsys.readouterr().err

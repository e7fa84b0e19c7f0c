"""Which matches does each pipeline hand the mapper, and how right are they? Measured against ground-truth cameras.

For photos with Strecha camera files (intrinsics and poses; images may be a scaled copy of the
size the files are for), every ``dqm sfm`` configuration given is run up to its COLMAP database
(``--pipelines``, as in scripts/bench_sfm.py; COLMAP's own pipeline too), and two things are
measured with the true cameras, independently of any mapper:

* the **verified matches** in the database (the inliers of COLMAP's two-view verification, what
  the mapper reads): their Sampson distance to the true epipolar geometry in pixels (median,
  90th percentile, share above 1 and 2 px). A precise match has a small distance; a wrong match
  along the epipolar line is not caught by this measure;
* the **clusters** (dqm's CLUSTERS file): each cluster of 2+ features is triangulated with the
  true cameras (linear, all members) and every member's reprojection error is taken; a cluster
  holds a *wrong member* when one of them is more than 2 px off. Reported: the share of clusters
  with a wrong member and how far off such members are (the median of the worst member).

Also each configuration's matches that the first dqm row's lack ("added") are scored alone, which
isolates what a step such as guided growth adds (only between rows with the same features). dqm
rows run with ``--no-triangulate`` (the database as the mapper read it) unless ``--triangulate``
is given: then the database also holds the model-guided matches of the last stage, and "added"
scores those.

    python scripts/sfm_match_truth.py --images ../shared/data/strecha/entry-P10/images \\
        --gt ../shared/data/strecha/entry-P10/gt_cameras --pipelines "colmap,dqm,dqm --guided,dqm --verify"
"""
from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

#: a cluster member more than this far (px) from its cluster's triangulated point counts as wrong
WRONG_PX = 2.0


def true_cameras(gt: Path, names: list[str], sizes: dict[str, tuple[int, int]]) -> dict[str, np.ndarray]:
    """3x4 projection matrices (OpenCV pixel convention) of the named images, K scaled to the image size."""
    from dqm.vision import poses

    out = {}
    for n in names:
        pose, K, (w0, h0) = poses.read_strecha_camera(gt / f"{n}.camera")
        w, h = sizes[n]
        K = K.copy()
        K[0] *= w / w0
        K[1] *= h / h0
        K[0, 2] += 0.5 * w / w0 - 0.5  # pixel centres: (x + 0.5) scales, OpenCV's centre is at 0
        K[1, 2] += 0.5 * h / h0 - 0.5
        out[n] = K @ np.c_[pose.R, pose.t]
    return out


def fundamental(Pa: np.ndarray, Pb: np.ndarray) -> np.ndarray:
    """F with x_b^T F x_a = 0 from two projection matrices (Hartley & Zisserman 9.2.2)."""
    C = np.linalg.svd(Pa)[2][-1]
    e = Pb @ C
    ex = np.array([[0, -e[2], e[1]], [e[2], 0, -e[0]], [-e[1], e[0], 0]])
    return ex @ Pb @ np.linalg.pinv(Pa)


def sampson(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    ha, hb = np.c_[xa, np.ones(len(xa))], np.c_[xb, np.ones(len(xb))]
    fx, fty = ha @ F.T, hb @ F
    return np.abs((hb * fx).sum(1)) / np.sqrt(fx[:, 0] ** 2 + fx[:, 1] ** 2 + fty[:, 0] ** 2 + fty[:, 1] ** 2)


def verified_matches(database: Path) -> dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """{(name a, name b): (xa, xb, (m, 2) keypoint indices)} of the database's verified inlier matches."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        images = {im.image_id: im.name for im in db.read_all_images()}
        kp = {i: np.asarray(db.read_keypoints(i))[:, :2] - 0.5 for i in images}  # COLMAP's +0.5 undone
        pair_ids, geometries = db.read_two_view_geometries()
        out = {}
        for pid, g in zip(pair_ids, geometries):
            i, j = pycolmap.pair_id_to_image_pair(pid)
            m = np.asarray(g.inlier_matches)
            if len(m):
                out[(images[i], images[j])] = (kp[i][m[:, 0]], kp[j][m[:, 1]], m)
    finally:
        db.close()
    return out


def match_errors(matches: dict, P: dict, keep=None) -> np.ndarray:
    """Sampson distances (px) of the matches to the true geometry; ``keep(pair, m)`` masks a subset."""
    out = []
    for (a, b), (xa, xb, m) in matches.items():
        sel = np.ones(len(m), bool) if keep is None else keep((a, b), m)
        if sel.any():
            out.append(sampson(fundamental(P[a], P[b]), xa[sel], xb[sel]))
    return np.concatenate(out) if out else np.zeros(0)


def cluster_errors(clusters: Path, P: dict) -> tuple[int, np.ndarray]:
    """The number of clusters of 2+ features and the worst member's reprojection error (px) of each."""
    from dqm import io

    z = io.load_clusters(clusters)
    labels, ids, kp = z["labels"], z["image_ids"], z["keypoints"][:, :2].astype(np.float64)
    names = [Path(str(n)).name for n in z["image_names"]]
    Ps = np.stack([P[n] for n in names])
    order = np.argsort(labels, kind="stable")
    cuts = np.r_[0, np.flatnonzero(np.diff(labels[order])) + 1, len(order)]
    worst = []
    for s, e in zip(cuts[:-1], cuts[1:]):
        if e - s < 2:
            continue
        mem = order[s:e]
        Pm, x = Ps[ids[mem]], kp[mem]
        A = np.concatenate([x[:, :1] * Pm[:, 2] - Pm[:, 0], x[:, 1:2] * Pm[:, 2] - Pm[:, 1]])
        X = np.linalg.svd(A)[2][-1]
        proj = Pm @ X
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.hypot(*(proj[:, :2] / proj[:, 2:3] - x).T)
        worst.append(np.nanmax(np.where(np.isfinite(err), err, np.inf)))
    return len(worst), np.array(worst)


def summary(e: np.ndarray) -> dict:
    if len(e) == 0:
        return {"n": 0}
    return {"n": int(len(e)), "median": float(np.median(e)), "p90": float(np.percentile(e, 90)),
            "over_1px": float(np.mean(e > 1)), "over_2px": float(np.mean(e > 2))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=Path, required=True)
    ap.add_argument("--gt", type=Path, required=True, help="Strecha *.camera files (intrinsics and poses)")
    ap.add_argument("--pipelines", default="colmap,dqm,dqm --triangulate,dqm --guided,dqm --verify",
                    help="comma-separated: colmap, or dqm sfm command lines ('dqm', 'dqm --guided', ...); the "
                         "first dqm one is the reference for 'added'")
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = ap.parse_args()
    try:
        import pycolmap
    except ImportError:
        sys.exit("sfm_match_truth: needs pycolmap (pip install 'dqm[colmap]')")
    from dqm.vision.features import collect_images
    from dqm.vision.sfm import colmap_pipeline

    paths = collect_images([str(args.images)])
    sizes = {}
    for p in paths:
        bitmap = pycolmap.Bitmap.read(str(p), False)
        sizes[p.name] = (int(bitmap.width), int(bitmap.height))
    P = true_cameras(args.gt, [p.name for p in paths], sizes)
    rows = {}
    reference = None
    with tempfile.TemporaryDirectory(prefix="dqm-match-truth-") as tmp:
        for k, name in enumerate(x.strip() for x in args.pipelines.split(",") if x.strip()):
            work = Path(tmp) / f"run{k}"
            if name == "colmap":
                colmap_pipeline(args.images, work, seed=0)
                database, clusters = work / "database.db", None
            else:
                options = shlex.split(name)[1:]
                if "--triangulate" not in options:  # the database as the mapper read it
                    options.append("--no-triangulate")
                cmd = [sys.executable, "-m", "dqm", "sfm", str(args.images), "--out", str(work), "--quiet",
                       *options]
                p = subprocess.run(cmd, capture_output=True, text=True)
                if p.returncode != 0:
                    sys.exit(f"sfm_match_truth: {name} failed: {p.stderr.strip()[-300:]}")
                database, clusters = work / "database.db", work / "clusters.npz"
            matches = verified_matches(database)
            row = {"verified_matches": summary(match_errors(matches, P))}
            if clusters is not None:
                n, worst = cluster_errors(clusters, P)
                bad = worst > WRONG_PX
                row["clusters"] = {"n": n, "with_wrong_member": float(bad.mean()) if n else 0.0,
                                   "wrong_member_median_px": float(np.median(worst[bad])) if bad.any() else 0.0}
                from dqm import io

                keypoints = io.load_clusters(clusters)["keypoints"]
                if reference is None:
                    reference = {pair: set(map(tuple, m.tolist())) for pair, (_, _, m) in matches.items()}
                    reference_keypoints = keypoints
                elif np.array_equal(keypoints, reference_keypoints):  # the same features: "added" means something
                    def added(pair, m, ref=reference):
                        have = ref.get(pair, set())
                        return np.array([tuple(r) not in have for r in m.tolist()], bool)

                    row["added_matches"] = summary(match_errors(matches, P, added))
            rows[name] = row
            v = row["verified_matches"]
            line = (f"{name}: {v['n']:,} verified matches, Sampson distance to the true geometry median "
                    f"{v['median']:.3f} px, p90 {v['p90']:.3f} px, > 1 px {v['over_1px']:.1%}, > 2 px "
                    f"{v['over_2px']:.1%}")
            if "added_matches" in row and row["added_matches"]["n"]:
                a = row["added_matches"]
                line += (f"; the {a['n']:,} not in the first dqm row's: median {a['median']:.3f} px, p90 "
                         f"{a['p90']:.3f} px, > 1 px {a['over_1px']:.1%}")
            if "clusters" in row:
                c = row["clusters"]
                line += (f"; clusters of 2+: {c['n']:,}, {c['with_wrong_member']:.1%} with a member > {WRONG_PX:g} px "
                         f"off (median worst {c['wrong_member_median_px']:.1f} px)")
            print(line, flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Where COLMAP triangulates a 3-D point that dqm sfm does not, and why (issue 61, item 3).

Both pipelines run on the same photos (``dqm sfm`` with the given options, COLMAP's own pipeline as
``scripts/bench_sfm.py`` runs it, both seeded). The two use different SIFT, so COLMAP's points are
followed through dqm's features by position: each observation of a COLMAP point takes dqm's nearest
keypoint in that image within ``--radius`` px (its *counterpart*). Every COLMAP point with a track of
2+ images then falls in the first class that holds:

* ``ours too``: two of its counterparts are observations of one of dqm's 3-D points;
* ``no counterpart``: fewer than two of its observations have a dqm keypoint near them (the detectors
  differ);
* ``in two of our points``: counterparts are observations of different dqm points (a track split);
* ``one cluster, not triangulated``: two counterparts share a QuickMatch cluster but no dqm point holds
  both; split into ``verified`` (the pair's match is an inlier in dqm's database: the mapper or the
  triangulation stage left it) and ``rejected`` (COLMAP's verification of the pair rejected it);
* ``alone in its cluster``: no two counterparts share a cluster and all but at most one are alone in
  theirs (QuickMatch kept the features apart: their descriptors did not stand out in the whole set);
* ``in other clusters``: no two share a cluster, and two or more sit in clusters with other members.

Each class is reported as a count and a share of COLMAP's points, with the mean track length.

    python scripts/sfm_points_gap.py --images ../shared/data/strecha/entry-P10/images \\
        --json docs/sfm/entry-P10-points-gap.json
    python scripts/sfm_points_gap.py --images ../shared/data/sacre_coeur --json docs/sfm/sacre_coeur-points-gap.json
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

CLASSES = ("ours too", "no counterpart", "in two of our points", "one cluster, not triangulated: verified",
           "one cluster, not triangulated: rejected", "alone in its cluster", "in other clusters")


def _feature_rows(image_ids: np.ndarray) -> list[np.ndarray]:
    """Per image index, its features' indices in order: a COLMAP point2D index of dqm's export is a position here."""
    return [np.flatnonzero(image_ids == k) for k in range(int(image_ids.max()) + 1)]


def _dqm_points(rec, names: list[str], rows: list[np.ndarray], n: int) -> np.ndarray:
    """Per dqm feature, the id of the dqm 3-D point that observes it (-1: none)."""
    index = {Path(nm).name: k for k, nm in enumerate(names)}
    point = np.full(n, -1, np.int64)
    for pid, p in rec.points3D.items():
        for el in p.track.elements:
            k = index[rec.images[el.image_id].name]
            point[rows[k][el.point2D_idx]] = pid
    return point


def _verified(database: Path, names: list[str], rows: list[np.ndarray]) -> set[tuple[int, int]]:
    """The feature pairs (lower index first) that are inliers of a two-view geometry in dqm's database."""
    from sfm_match_truth import verified_matches  # this folder's: the database's verified inlier matches

    index = {Path(nm).name: k for k, nm in enumerate(names)}
    out = set()
    for (a, b), (_, _, m) in verified_matches(database).items():
        fa, fb = rows[index[a]][m[:, 0]], rows[index[b]][m[:, 1]]
        out.update(zip(np.minimum(fa, fb).tolist(), np.maximum(fa, fb).tolist()))
    return out


def _largest_model(sparse: Path):
    """The largest of the models in a mapper's output folder (``sparse/0``, ``sparse/1``, ...), as dqm sfm
    and the benchmark rank them (:func:`dqm.vision.sfm.largest`)."""
    import pycolmap

    from dqm.vision.sfm import largest

    recs = {p.name: pycolmap.Reconstruction(str(p)) for p in sorted(sparse.iterdir()) if p.is_dir()}
    return recs[largest(recs)]


def classify(colmap_rec, keypoints, image_ids, names, labels, point, verified, radius: float) -> dict:
    """Each COLMAP point of 2+ images in its class (module docstring): counts and mean track lengths."""
    from scipy.spatial import cKDTree

    index = {Path(nm).name: k for k, nm in enumerate(names)}
    rows = _feature_rows(image_ids)
    trees = [cKDTree(keypoints[r, :2]) for r in rows]
    size = np.bincount(labels)
    out = {c: [0, 0] for c in CLASSES}
    for p in colmap_rec.points3D.values():
        if p.track.length() < 2:
            continue
        found = []
        for el in p.track.elements:
            image = colmap_rec.images[el.image_id]
            k = index.get(image.name)
            if k is None:
                continue
            xy = np.asarray(image.points2D[el.point2D_idx].xy) - 0.5  # COLMAP's pixel centres -> OpenCV's
            d, j = trees[k].query(xy)
            if d <= radius:
                found.append(int(rows[k][j]))
        c = _class_of(found, labels, size, point, verified)
        out[c][0] += 1
        out[c][1] += p.track.length()
    total = sum(v[0] for v in out.values())
    return {"colmap_points": total,
            "classes": {c: {"points": v[0], "share": v[0] / max(total, 1), "mean_track": v[1] / max(v[0], 1)}
                        for c, v in out.items()}}


def _class_of(found: list[int], labels, size, point, verified) -> str:
    pts = point[found]
    seen = pts[pts >= 0]
    if len(seen) != len(np.unique(seen)):
        return "ours too"
    if len(found) < 2:
        return "no counterpart"
    if len(np.unique(seen)) >= 2:
        return "in two of our points"
    labs = labels[found]
    if len(np.unique(labs)) < len(labs):
        for x in range(len(found)):
            for y in range(x + 1, len(found)):
                if labs[x] == labs[y] and (min(found[x], found[y]), max(found[x], found[y])) in verified:
                    return "one cluster, not triangulated: verified"
        return "one cluster, not triangulated: rejected"
    if (size[labs] > 1).sum() <= 1:
        return "alone in its cluster"
    return "in other clusters"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", required=True, help="the photos (one folder)")
    ap.add_argument("--dqm-options", default="", help="options of dqm sfm (default: none, its defaults)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--radius", type=float, default=2.0, help="px from a COLMAP observation to its counterpart")
    ap.add_argument("--json", default=None, help="write the numbers here")
    ap.add_argument("--work", default=None, help="keep both pipelines' outputs here and reuse them on the next run "
                                                  "(default: a temporary folder)")
    args = ap.parse_args()

    from dqm import io
    from dqm.vision.sfm import colmap_pipeline

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        cmd = [sys.executable, "-m", "dqm", "sfm", args.images, "--out", str(work / "dqm"), "--quiet",
               "--seed", str(args.seed), *shlex.split(args.dqm_options)]
        if not (work / "dqm" / "sfm.json").exists():
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        c = io.load_clusters(work / "dqm" / "clusters.npz")
        keypoints, image_ids, labels = np.asarray(c["keypoints"]), np.asarray(c["image_ids"]), np.asarray(c["labels"])
        names = [str(x) for x in c["image_names"]]
        rows = _feature_rows(image_ids)
        rec = _largest_model(work / "dqm" / "sparse")
        point = _dqm_points(rec, names, rows, len(labels))
        verified = _verified(work / "dqm" / "database.db", names, rows)
        if not (work / "colmap" / "sparse").exists():
            colmap_pipeline(args.images, work / "colmap", seed=args.seed)
        colmap_rec = _largest_model(work / "colmap" / "sparse")
        result = classify(colmap_rec, keypoints, image_ids, names, labels, point, verified, args.radius)
    result.update(images=args.images, dqm_options=args.dqm_options, seed=args.seed, radius=args.radius,
                  dqm_points=len(rec.points3D), colmap_model_points=len(colmap_rec.points3D))
    print(f"{args.images}: COLMAP {result['colmap_model_points']:,} points, dqm {result['dqm_points']:,}; "
          f"COLMAP's points by what dqm made of them (counterparts within {args.radius:g} px):")
    print("| class | COLMAP points | share | mean track |\n|---|---|---|---|")
    for name, v in result["classes"].items():
        print(f"| {name} | {v['points']:,} | {v['share']:.3f} | {v['mean_track']:.2f} |")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Run QuickMatch on a generated multi-image SIFT-like descriptor set (no download)
and score it against the generator's exact ground truth.

    dqm demo [--images 8] [--points 500] [--seed 0]
"""
from __future__ import annotations

import warnings

from .. import evaluation, synthetic
from ..core import quickmatch
from ..core.params import DEFAULT_KERNEL
from .param_options import add_quickmatch_params

NAME = "demo"
HELP = "QuickMatch on generated data with known ground truth"


def add_arguments(p) -> None:
    p.add_argument("--images", type=int, default=8, help="number of views")
    p.add_argument("--points", type=int, default=500, help="physical points in the scene")
    p.add_argument("--clutter", type=int, default=150, help="unmatched features per image")
    p.add_argument("--noise", type=float, default=0.35,
                   help="per-view descriptor noise relative to a typical component (0.25: about real SIFT)")
    add_quickmatch_params(p, ("rho",), notes={"rho": f" ({DEFAULT_KERNEL} kernel, as dqm match)"})
    p.add_argument("--seed", type=int, default=0, help="generator seed")


def run(args) -> int:
    ds = synthetic.sift_like(n_images=args.images, n_points=args.points, clutter_per_image=args.clutter,
                             noise=args.noise, seed=args.seed)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = quickmatch(ds.descriptors, ds.image_ids, rho=args.rho)
    for w in caught:  # one plain line each, not Python's warning format
        print(f"note: {str(w.message).removeprefix('quickmatch: ')}")
    s = evaluation.cluster_scores_landmarks(r.labels, ds.point_ids, ds.image_ids)
    print(r.summary())
    if s.n_truth == 0:
        print(f"Against ground truth: no true pairs to find (--points {args.points}, --images {args.images}); "
              f"{s.n_predicted} pairs predicted, all of them wrong." if s.n_predicted else
              "Against ground truth: no true pairs and none predicted.")
        return 0
    print(f"Against ground truth: pairwise precision {s.precision:.3f}, recall {s.recall:.3f}, F1 {s.f1:.3f} "
          f"({s.n_correct} of {s.n_predicted} predicted pairs correct, {s.n_truth} true pairs).")
    return 0

#!/usr/bin/env python
"""The seed paper's synthetic illustration of Distributed QuickMatch, as PNGs.

2-D data: 25 Gaussian clusters of 10 points on a 5 x 5 grid (point k of every
cluster comes from "image" k), 4 agents with k-means seeds. Writes to
docs/img/: dqm2d_partition.png (cells and seeds), dqm2d_boundary.png
(contested points), dqm2d_local.png (per-agent clusters), dqm2d_handdown.png
(proposed hand-downs), dqm2d_final.png (final clusters vs centralized) for the
lean and paper modes' cascade; dqm2d_balanced.png (power cells, ghost copies,
the parent forest and its crossing edges, final clusters) for the balanced mode.

    python scripts/dqm_illustration.py [--seed 3] [--mode lean|paper|balanced] [--out dqm-out/img]
"""
import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import dqm  # noqa: E402
from dqm.distributed import DQMConfig, partition, simulate  # noqa: E402
from dqm.evaluation import comembership_scores  # noqa: E402


def data(seed: int):
    rng = np.random.default_rng(seed)
    centers = np.stack(np.meshgrid(np.arange(5), np.arange(5)), -1).reshape(-1, 2) * 10.0
    X = np.repeat(centers, 10, axis=0) + rng.normal(0.0, 1.2, size=(250, 2))
    ids = np.tile(np.arange(10), 25)
    return X, ids


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--mode", default="lean", choices=["lean", "paper", "balanced"])
    ap.add_argument("--out", default="dqm-out/img", help="folder for the PNGs (docs/img regenerates the docs')")
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    X, ids = data(args.seed)
    r = simulate(X, ids, DQMConfig(agents=4, seed=args.seed, mode=args.mode, samples_per_agent=64))
    central = dqm.quickmatch(X, ids, kernel="quadratic")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    colors = plt.get_cmap("tab10")
    xs = np.linspace(X[:, 0].min() - 5, X[:, 0].max() + 5, 300)
    ys = np.linspace(X[:, 1].min() - 5, X[:, 1].max() + 5, 300)
    G = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    cell_img = partition.route(G, r.sites, r.weights).reshape(len(ys), len(xs))

    def base(title):
        fig, ax = plt.subplots(figsize=(6, 6))
        ax.imshow(cell_img, origin="lower", extent=(xs[0], xs[-1], ys[0], ys[-1]), cmap="Pastel1",
                  vmin=0, vmax=8, alpha=0.6)
        ax.contour(xs, ys, cell_img, levels=np.arange(0.5, 4), colors="k", linewidths=0.8)
        ax.scatter(*r.sites.T, marker="*", s=250, c=[colors(a) for a in range(4)], edgecolors="k", zorder=5)
        for a, p in enumerate(r.sites):
            ax.annotate(f"agent {a}", p, xytext=(6, 6), textcoords="offset points", weight="bold")
        ax.set_title(title)
        ax.set_aspect("equal")
        return fig, ax

    if args.mode == "balanced":
        return balanced_figure(plt, X, r, central, cell_img, xs, ys, colors, out)
    fig, ax = base("partition: Voronoi cells of the seeds, points by cell")
    ax.scatter(*X.T, c=[colors(c) for c in r.cells], s=14)
    fig.savefig(out / "dqm2d_partition.png", dpi=100)
    fig, ax = base("contested points (may interact with another cell)")
    ax.scatter(*X[~r.contested].T, c="lightgray", s=12)
    ax.scatter(*X[r.contested].T, c="red", s=18, label=f"contested ({r.contested.sum()})")
    ax.legend(loc="upper right")
    fig.savefig(out / "dqm2d_boundary.png", dpi=100)
    fig, ax = base("per-agent clusters before hand-down")
    lab = r.initial_labels
    rng = np.random.default_rng(0)
    palette = rng.random((lab.max() + 1, 3)) * 0.8
    ax.scatter(*X.T, c=palette[lab], s=16)
    fig.savefig(out / "dqm2d_local.png", dpi=100)
    fig, ax = base("proposed hand-downs (arrow to the receiving agent's seed)")
    ax.scatter(*X.T, c=[colors(c) for c in r.cells], s=10)
    moved = np.flatnonzero(r.handed_to >= 0)
    for k in moved:
        ax.annotate("", r.sites[r.handed_to[k]], X[k], arrowprops=dict(arrowstyle="->", alpha=0.35, lw=0.7))
    ax.set_xlabel(f"{len(moved)} points handed down")
    fig.savefig(out / "dqm2d_handdown.png", dpi=100)
    s = comembership_scores(r.labels, central.labels)
    fig, ax = base(f"final clusters (F1 vs centralized {s.f1:.3f})")
    palette = rng.random((r.labels.max() + 1, 3)) * 0.8
    ax.scatter(*X.T, c=palette[r.labels], s=16)
    for a in range(4):
        held = r.holder == a
        if held.any():
            ax.scatter(*X[held].T, facecolors="none", edgecolors=[colors(a)], s=60, lw=0.6)
    fig.savefig(out / "dqm2d_final.png", dpi=100)
    plt.close("all")
    print(f"{len(X)} points, 4 agents ({args.mode} mode): {int(r.contested.sum())} contested, "
          f"{len(moved)} handed down, "
          f"{r.n_clusters} final clusters vs {central.n_clusters} centralized, co-membership F1 {s.f1:.3f}; "
          f"PNGs in {out}")


def balanced_figure(plt, X, r, central, cell_img, xs, ys, colors, out):
    """One PNG with three panels: copies, the parent forest, the final clusters."""
    from matplotlib.colors import ListedColormap

    tint = ListedColormap([colors(a) for a in range(4)])
    fig, axes = plt.subplots(1, 3, figsize=(17, 6.2))
    for ax in axes:
        ax.imshow(cell_img, origin="lower", extent=(xs[0], xs[-1], ys[0], ys[-1]), cmap=tint,
                  vmin=-0.5, vmax=3.5, alpha=0.15)
        ax.contour(xs, ys, cell_img, levels=np.arange(0.5, 4), colors="k", linewidths=0.8)
        ax.scatter(*r.sites.T, marker="*", s=200, c=[colors(a) for a in range(4)], edgecolors="k", zorder=5)
        ax.set_aspect("equal")
    ax = axes[0]
    ax.scatter(*X.T, c=[colors(c) for c in r.cells], s=12)
    for k, b in r.copies.tolist():
        ax.annotate("", r.sites[b], X[k], arrowprops=dict(arrowstyle="->", color=colors(b), alpha=0.35, lw=0.6))
    ax.set_title(f"power cells (largest {r.stats['largest_cell_share']:.2f} n/m) and {len(r.copies)} ghost copies\n"
                 "(arrow: copy sent one way to the receiving cell)")
    ax = axes[1]
    child = np.flatnonzero(r.parent >= 0)
    par = r.parent[child]
    crossing = r.cells[child] != r.cells[par]
    for k, p_, c in zip(child.tolist(), par.tolist(), crossing.tolist()):
        ax.plot(*np.stack([X[k], X[p_]]).T, color="red" if c else "0.3", lw=1.4 if c else 0.7)
    ax.scatter(*X.T, c=[colors(c) for c in r.cells], s=12, zorder=3)
    ax.set_title(f"parent forest: {int(crossing.sum())} of {len(child)} edges cross cells (red);\n"
                 "only their components travel (edge lists, no descriptors)")
    ax = axes[2]
    same = bool(np.array_equal(r.labels, central.labels))
    palette = np.random.default_rng(0).random((r.labels.max() + 1, 3)) * 0.8
    ax.scatter(*X.T, c=palette[r.labels], s=16)
    moved = r.holder != r.cells
    ax.scatter(*X[moved].T, facecolors="none", edgecolors="k", s=60, lw=0.6)
    ax.set_title(f"final clusters: {'identical to' if same else 'DIFFERENT from'} centralized\n"
                 f"(ringed: {int(moved.sum())} decided by another agent)")
    fig.tight_layout()
    fig.savefig(out / "dqm2d_balanced.png", dpi=100)
    plt.close("all")
    print(f"{len(X)} points, 4 agents (balanced mode): {len(r.copies)} copies, {int(crossing.sum())} crossing edges, "
          f"labels {'identical to' if same else 'different from'} centralized; {out / 'dqm2d_balanced.png'}")


if __name__ == "__main__":
    main()

"""Figures of matches and of their evaluation (matplotlib, Agg: files only, no display).

Every function returns a :class:`matplotlib.figure.Figure` built without
pyplot (no global state, safe in threads and on headless machines); save it
with :func:`save`.

* :func:`pair_figure` - two images side by side with a line per match
  (green / red when correctness is known);
* :func:`clusters_figure` - one row per cluster: the cluster's feature in each
  of its images (a patch around the keypoint, its scale circled);
* :func:`cluster_sizes_figure` - histogram of cluster sizes;
* :func:`pr_figure` - precision-recall curves of several methods, each with its
  default operating point marked.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .evaluation import PRCurve
from .validation import InputError
from .vision.features import as_gray


def _figure(width: float, height: float, dpi: int = 100):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def save(fig, path, dpi: int = 100) -> Path:
    """Write a figure (format from the suffix, e.g. .png) and return the path."""
    from .outputs import atomic_output

    p = Path(path)
    with atomic_output(p) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format=p.suffix.lstrip(".").lower() or None)
    return p


def pair_figure(image_a, image_b, xy_a, xy_b, correct: np.ndarray | None = None, *,
                title: str = "", max_lines: int = 300, seed: int = 0):
    """Two images side by side with a line for every match (xy_a[k] <-> xy_b[k]).

    ``correct``: optional boolean per match (green correct, red wrong; otherwise
    one colour per line). More than ``max_lines`` matches are subsampled
    (deterministically, ``seed``) and the title says so.
    """
    A, B = as_gray(image_a), as_gray(image_b)
    xy_a = np.asarray(xy_a, float).reshape(-1, 2) if len(xy_a) else np.zeros((0, 2))
    xy_b = np.asarray(xy_b, float).reshape(-1, 2) if len(xy_b) else np.zeros((0, 2))
    if len(xy_a) != len(xy_b):
        raise InputError(f"xy_a and xy_b must have one row per match ({len(xy_a)} vs {len(xy_b)})")
    if correct is not None and len(correct) != len(xy_a):
        raise InputError("correct must have one entry per match")
    h = max(A.shape[0], B.shape[0])
    canvas = np.full((h, A.shape[1] + B.shape[1]), 255, np.uint8)
    canvas[:A.shape[0], :A.shape[1]] = A
    canvas[:B.shape[0], A.shape[1]:] = B
    n = len(xy_a)
    idx = np.arange(n)
    if n > max_lines:
        idx = np.sort(np.random.default_rng(seed).choice(n, max_lines, replace=False))
    fig = _figure(12, 12 * h / canvas.shape[1] + 0.6)
    ax = fig.add_axes([0, 0, 1, 0.95])
    ax.imshow(canvas, cmap="gray", vmin=0, vmax=255)
    ax.set_axis_off()
    off = A.shape[1]
    if correct is not None:
        colors = np.where(np.asarray(correct, bool)[idx], "#1a9850", "#d73027")
    else:
        from matplotlib import colormaps

        cmap = colormaps["hsv"]
        colors = [cmap(k / max(1, len(idx))) for k in range(len(idx))]
    for c, k in zip(colors, idx):
        ax.plot([xy_a[k, 0], xy_b[k, 0] + off], [xy_a[k, 1], xy_b[k, 1]], "-", color=c, lw=0.7, alpha=0.8)
    ax.plot(xy_a[idx, 0], xy_a[idx, 1], "o", ms=2, mfc="none", mec="yellow", mew=0.6)
    ax.plot(xy_b[idx, 0] + off, xy_b[idx, 1], "o", ms=2, mfc="none", mec="yellow", mew=0.6)
    note = f"{n} matches" + (f" ({len(idx)} drawn)" if len(idx) < n else "")
    if correct is not None and n:
        note += f", {int(np.sum(correct))} correct ({100.0 * np.mean(correct):.1f}%)"
    ax.set_title(f"{title}  {note}".strip(), fontsize=10)
    return fig


def _patch(img: np.ndarray, x: float, y: float, radius: int) -> np.ndarray:
    """Square crop of side 2*radius+1 centred on (x, y), padded with grey outside the image."""
    xi, yi = int(round(x)), int(round(y))
    out = np.full((2 * radius + 1, 2 * radius + 1), 128, np.uint8)
    y0, y1 = max(0, yi - radius), min(img.shape[0], yi + radius + 1)
    x0, x1 = max(0, xi - radius), min(img.shape[1], xi + radius + 1)
    if y0 < y1 and x0 < x1:
        out[y0 - (yi - radius):y1 - (yi - radius), x0 - (xi - radius):x1 - (xi - radius)] = img[y0:y1, x0:x1]
    return out


def clusters_figure(images: Sequence, keypoints, image_ids, clusters: Sequence[np.ndarray], *,
                    radius: int = 32, title: str = "", point_ids: np.ndarray | None = None,
                    max_columns: int = 12):
    """One row per cluster: a patch around each of its features, in image order.

    ``images[k]`` is the image (path or array) of image id k; ``keypoints``
    (n, 2..4) x, y[, size]; ``clusters`` lists feature indices. A cluster with
    more than ``max_columns`` features shows that many, evenly spread over its
    images. With ``point_ids`` (ground truth), a patch whose point differs
    from the cluster's most common one gets a red frame.

    The patches are one mosaic image in one axes (their scales circled and
    centres marked by one collection each), not an axes per patch: the camnet
    report's 12 clusters (up to 4 patches) draw and save in a third of the time.
    """
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    kp = np.asarray(keypoints, float)
    ids = np.asarray(image_ids)
    if not len(clusters):
        raise InputError("no clusters to draw")
    if max_columns < 1:
        raise InputError("max_columns must be >= 1")
    cols = min(max_columns, max(len(c) for c in clusters))
    rows = len(clusters)
    side = 2 * radius + 1
    gap = max(2, side // 4)  # between patches: room for a title above each
    step = side + gap
    mosaic = np.full((rows * step, cols * step - gap + 2, 3), 255, np.uint8)
    cache: dict[int, np.ndarray] = {}
    rings, centres, titles = [], [], []
    for r, members in enumerate(clusters):
        members = np.asarray(members)[np.argsort(ids[np.asarray(members)], kind="stable")]
        majority = None
        if point_ids is not None:
            vals, cnt = np.unique(np.asarray(point_ids)[members], return_counts=True)
            majority = vals[np.argmax(cnt)]
        shown = members
        if len(members) > cols:
            shown = members[np.unique(np.round(np.linspace(0, len(members) - 1, cols)).astype(int))]
        for c, f in enumerate(shown):
            k = int(ids[f])
            if k not in cache:
                cache[k] = as_gray(images[k])
            y0, x0 = r * step + gap, c * step + 1
            wrong = majority is not None and np.asarray(point_ids)[f] != majority
            frame = 3 if wrong else 1
            mosaic[y0 - frame:y0 + side + frame, x0 - frame:x0 + side + frame] = (215, 48, 39) if wrong else 0
            mosaic[y0:y0 + side, x0:x0 + side] = _patch(cache[k], kp[f, 0], kp[f, 1], radius)[:, :, None]
            if kp.shape[1] >= 3 and kp[f, 2] > 0:
                rings.append(Circle((x0 + radius, y0 + radius), kp[f, 2] / 2.0))
            centres.append((x0 + radius, y0 + radius))
            titles.append((x0 + radius, y0 - frame - 1, f"img {k}" if c else f"[{len(members)}] img {k}"))
    fig = _figure(1.3 * cols + 0.4, 1.45 * rows + 0.5)
    ax = fig.add_axes((0.02, 0.02, 0.96, 0.96 if not title else 0.9))
    ax.imshow(mosaic, interpolation="nearest")
    if rings:
        ax.add_collection(PatchCollection(rings, facecolor="none", edgecolor="yellow", linewidth=0.8))
    ax.plot(*np.asarray(centres).T, "+", color="yellow", ms=5, ls="")
    for x, y, text in titles:
        ax.text(x, y, text, fontsize=7, ha="center", va="bottom")
    ax.set_xlim(0, mosaic.shape[1])
    ax.set_ylim(mosaic.shape[0], 0)
    ax.set_axis_off()
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def cluster_sizes_figure(labels, image_ids=None, *, title: str = "Cluster sizes"):
    """Bar chart: number of clusters of each size (log scale), with the features they hold."""
    labels = np.asarray(labels)
    if labels.ndim != 1 or len(labels) == 0:
        raise InputError("labels must be a non-empty 1-D array")
    sizes = np.bincount(np.unique(labels, return_inverse=True)[1].ravel())
    hist = np.bincount(sizes)
    s = np.flatnonzero(hist)
    fig = _figure(6.5, 3.8)
    ax = fig.add_subplot(1, 1, 1)
    bars = ax.bar(s, hist[s], color="#4575b4")
    ax.set_yscale("log")
    ax.set_xlabel("cluster size (features = images, by C2)")
    ax.set_ylabel("number of clusters")
    ax.set_xticks(s if len(s) <= 30 else s[:: max(1, len(s) // 15)])
    for b, k in zip(bars, s):
        ax.annotate(f"{hist[k] * k}", (b.get_x() + b.get_width() / 2, b.get_height()), ha="center",
                    va="bottom", fontsize=7, color="#555")
    n_img = len(np.unique(image_ids)) if image_ids is not None else None
    sub = f"{len(labels)} features, {len(sizes)} clusters" + (f", {n_img} images" if n_img else "")
    ax.set_title(f"{title}\n{sub} (numbers on bars: features)", fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    return fig


_STYLE = {
    "quickmatch": {"color": "#d73027", "lw": 2.2, "marker": "o"},
    "quickmatch-verify": {"color": "#f46d43", "lw": 1.6, "marker": "D", "ms": 5},
    "quickmatch-guided": {"color": "#a50026", "lw": 1.8, "marker": "*", "ms": 8},
    "bf": {"color": "#4575b4", "lw": 1.2, "ls": ":", "marker": "."},
    "flann": {"color": "#74add1", "lw": 1.2, "ls": ":", "marker": "."},
    "bf-drop-track": {"color": "#1a9850", "lw": 1.4, "ls": "--", "marker": "s", "ms": 3},
    "bf-drop-later": {"color": "#984ea3", "lw": 1.4, "ls": "--", "marker": "^", "ms": 3},
    "flann-drop-track": {"color": "#a6d96a", "lw": 1.2, "ls": "-.", "marker": "s", "ms": 3},
    "flann-drop-later": {"color": "#c2a5cf", "lw": 1.2, "ls": "-.", "marker": "^", "ms": 3},
}


def pr_figure(curves: Sequence[PRCurve], points: dict[str, tuple[float, float]] | None = None, *,
              labels: dict[str, str] | None = None, title: str = ""):
    """Precision-recall curves (one per method); ``points[method] = (recall, precision)`` marked with a star.

    A curve of one point (no threshold sweep, e.g. QuickMatch geometrically
    verified) is drawn as that point, without an AUC in its legend entry.
    """
    if not curves:
        raise InputError("no curves to draw")
    fig = _figure(6.5, 5)
    ax = fig.add_subplot(1, 1, 1)
    for c in curves:
        style = dict(_STYLE.get(c.method, {"lw": 1.2, "marker": "."}))
        name = (labels or {}).get(c.method, c.method)
        order = np.argsort(c.thresholds)
        area = f" (AUC {c.auc():.3f})" if len(c.thresholds) > 1 else " (one point)"
        ax.plot(c.recall[order], c.precision[order], label=name + area, **style)
        if points and c.method in points:
            r, p = points[c.method]
            ax.plot([r], [p], marker="*", ms=13, color=style.get("color", "k"), mec="black", mew=0.6, ls="none")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    ax.set_title(title + ("\n" if title else "") + "stars: each method's default threshold", fontsize=10)
    return fig

"""The figures of a camera-network experiment (:func:`dqm.camnet.report.write_report` saves them).

Each function takes an :class:`~dqm.camnet.experiment.ExperimentResult` and returns a matplotlib
figure; the report module names the files (its docstring lists them).
"""
from __future__ import annotations

import math

import numpy as np

from ..plots import _figure, clusters_figure, pr_figure
from .experiment import ExperimentResult, detection_curve, localization_errors, operating_point
from .geometry import fov_wedge
from .pipeline import LABELS
from .summary import method_label

__all__ = ["clusters_patches_figure", "discovery_figure", "errors_figure", "pr_detection_figure",
           "pr_parameter_figure", "trajectories_figure", "views_figure"]

_COLORS = {"quickmatch": "#d73027", "bf": "#4575b4", "flann": "#74add1", "quickmatch-quadratic": "#fdae61",
           "quickmatch-online": "#762a83"}
#: PR-curve styles of the QuickMatch variants (the paper's methods use dqm.plots' styles)
_VARIANT_STYLE = {"quickmatch-quadratic": dict(color=_COLORS["quickmatch-quadratic"], lw=1.6, ls="--", marker="s",
                                               ms=4),
                  "quickmatch-online": dict(color=_COLORS["quickmatch-online"], lw=1.6, ls="-.", marker="^", ms=4)}
_CAM_COLORS = ["#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#66a61e", "#e6ab02", "#a6761d", "#666666"]


def _label(result: ExperimentResult, method: str) -> str:
    return method_label(result.pipeline, method)


def pr_detection_figure(result: ExperimentResult):
    curves = [detection_curve(result, m) for m in result.methods]
    pts = {}
    for m in result.methods:
        op = operating_point(result, m)
        pts[m] = (op["recall"], op["precision"])
    fig = pr_figure(curves, pts, labels={m: _label(result, m) for m in result.methods},
                    title=f"Target detection over the minimum match count "
                          f"({result.n_frames} frames, {result.n_positive} with the target visible)")
    _restyle_variants(fig, result)
    return fig


def _restyle_variants(fig, result: ExperimentResult) -> None:
    """Give the QuickMatch variants' curves (unknown to dqm.plots) their own colour, line and marker."""
    ax = fig.axes[0]
    labels = {_label(result, m): m for m in _VARIANT_STYLE if m in result.methods}
    lines = list(ax.get_lines())
    for k, line in enumerate(lines):
        name = str(line.get_label()).rsplit(" (AUC", 1)[0]
        if name not in labels:
            continue
        style = _VARIANT_STYLE[labels[name]]
        line.set(**style)
        if k + 1 < len(lines) and lines[k + 1].get_marker() == "*":  # its starred operating point
            lines[k + 1].set_color(style["color"])
    ax.legend(fontsize=7, loc="lower left")


def pr_parameter_figure(result: ExperimentResult):
    if not result.sweeps:
        return None
    k = result.pipeline.min_matches
    curves = [result.sweeps[m].curve(k) for m in result.methods if m in result.sweeps]
    if not curves:
        return None
    pts = {}
    for c in curves:
        default = result.pipeline.rho if c.method == "quickmatch" else result.pipeline.ratio
        j = int(np.argmin(np.abs(c.thresholds - default)))
        pts[c.method] = (c.recall[j], c.precision[j])
    labels = {"quickmatch": "QuickMatch over rho", "bf": "BF over ratio", "flann": "FLANN over ratio"}
    return pr_figure(curves, pts, labels=labels,
                     title=f"Target detection (>= {k} matches) over each method's matching parameter")


def _arena(ax, result: ExperimentResult) -> None:
    from matplotlib.patches import Polygon, Rectangle

    world = result.world
    ax_, ay_ = result.sim.arena
    ax.add_patch(Rectangle((-ax_ / 2, -ay_ / 2), ax_, ay_, fill=False, ec="black", lw=1.0))
    for b in world.clutter:
        w, d, _ = b.size
        f = np.array([math.cos(b.heading), math.sin(b.heading)])
        left = np.array([-f[1], f[0]])
        c = np.array(b.centre)
        poly = np.array([c + f * w / 2 + left * d / 2, c - f * w / 2 + left * d / 2,
                         c - f * w / 2 - left * d / 2, c + f * w / 2 - left * d / 2])
        ax.add_patch(Polygon(poly, closed=True, fc="#bbbbbb", ec="#888888", lw=0.5))
    if world.decoy is not None:
        cs = world.decoy.corners
        ax.plot(cs[:2, 0], cs[:2, 1], "-", color="#ff7f00", lw=4, solid_capstyle="butt")
        ax.annotate("decoy", cs[0, :2], fontsize=7, color="#ff7f00")
    for c, cam in enumerate(world.cameras):
        col = _CAM_COLORS[c % len(_CAM_COLORS)]
        wedge = fov_wedge(cam, 2.0)
        ax.add_patch(Polygon(wedge, closed=True, fc=col, alpha=0.12, ec=col, lw=0.6))
        ax.plot(*cam.position[:2], marker=(3, 0, math.degrees(cam.yaw) - 90), ms=9, color=col, ls="none")
        ax.annotate(f"c{c}", cam.position[:2], xytext=(4, 4), textcoords="offset points", fontsize=7, color=col)
    tr = world.trajectory
    ax.plot(tr[:, 0], tr[:, 1], "-", color="black", lw=1.4, label="true trajectory")
    ax.plot(tr[0, 0], tr[0, 1], "o", color="black", ms=4)


def trajectories_figure(result: ExperimentResult):
    n = len(result.methods)
    cols = min(n, 3)
    rows = int(math.ceil(n / cols))
    ax_, ay_ = result.sim.arena
    fig = _figure(4.6 * cols, (4.6 * ay_ / ax_ + 0.6) * rows + 0.4)
    for k, m in enumerate(result.methods):
        ax = fig.add_subplot(rows, cols, k + 1)
        _arena(ax, result)
        a = result.arrays(m)
        det = a["score"] >= result.pipeline.min_matches
        has = det & np.isfinite(a["estimate"]).all(axis=1)
        lim = np.array([ax_ / 2 + 0.8, ay_ / 2 + 0.8])
        outside = has & (np.abs(a["estimate"]) > lim).any(axis=1)
        for c in range(len(result.world.cameras)):
            col = _CAM_COLORS[c % len(_CAM_COLORS)]
            sel = has & (a["camera"] == c) & ~outside
            tp, fp = sel & a["visible"], sel & ~a["visible"]
            ax.plot(a["estimate"][tp, 0], a["estimate"][tp, 1], "o", ms=3.5, color=col, alpha=0.85, ls="none")
            ax.plot(a["estimate"][fp, 0], a["estimate"][fp, 1], "x", ms=5, color=col, ls="none")
        err = localization_errors(result, m)
        ax.set_xlim(-lim[0], lim[0])
        ax.set_ylim(-lim[1], lim[1])
        ax.set_aspect("equal")
        ax.grid(alpha=0.25)
        ax.set_xlabel("x (m)")
        if k % cols == 0:
            ax.set_ylabel("y (m)")
        ax.set_title(f"{_label(result, m)}\n{int(has.sum())} estimates, error {err.mean:.2f} +- {err.std:.2f} m"
                     + (f", {int(outside.sum())} off the plot" if outside.any() else ""), fontsize=9)
    fig.suptitle("Estimated target positions (dots: target visible, x: false detection; colour = camera)",
                 fontsize=10)
    return fig


def errors_figure(result: ExperimentResult, max_error: float = 3.0):
    fig = _figure(6.5, 4.2)
    ax = fig.add_subplot(1, 1, 1)
    bins = np.linspace(0, max_error, 31)
    for m in result.methods:
        e = localization_errors(result, m)
        vals = np.minimum(e.errors, max_error - 1e-9)
        ax.hist(vals, bins=bins, histtype="step", lw=1.8, color=_COLORS.get(m),
                label=f"{_label(result, m)}: {e.mean:.2f} +- {e.std:.2f} m (median {e.median:.2f}, n={len(e.errors)})")
    ax.set_xlabel(f"localization error (m; errors >= {max_error:g} m in the last bin)")
    ax.set_ylabel("detections")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    ax.set_title(f"Localization error of detections (>= {result.pipeline.min_matches} matches)", fontsize=10)
    return fig


def views_figure(result: ExperimentResult):
    snap = result.snapshot
    if snap is None:
        return None
    from matplotlib.patches import Rectangle

    R = len(result.world.references)
    cams = snap.images[R:]
    n = len(cams)
    cols = min(3, n)
    rows = int(math.ceil(n / cols))
    fig = _figure(4.2 * cols, 3.35 * rows + 0.4)
    for c, img in enumerate(cams):
        ax = fig.add_subplot(rows, cols, c + 1)
        ax.imshow(img, cmap="gray", vmin=0, vmax=255)
        tr = snap.truths[c]
        if tr.box is not None:
            x0, y0, x1, y1 = tr.box
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="#00c000", lw=2.2, ls="--"))
        lines = [f"cam {c}: target {'visible' if tr.visible else 'not visible'} ({tr.target_px} px)"]
        for m in result.methods:
            d = next(d for d in result.detections[m] if d.step == snap.step and d.camera == c)
            ok = d.score >= result.pipeline.min_matches
            if ok and d.box is not None:
                x0, y0, x1, y1 = d.box
                ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec=_COLORS[m], lw=1.3))
            lines.append(f"{LABELS[m]} {d.score}{' det' if ok else ''}")
        rest = [", ".join(lines[1 + j:4 + j]) for j in range(0, len(lines) - 1, 3)]
        ax.set_title("\n".join(lines[:1] + rest), fontsize=7)
        ax.set_xlim(0, img.shape[1])
        ax.set_ylim(img.shape[0], 0)
        ax.set_axis_off()
    colours = {"#d73027": "red", "#4575b4": "blue", "#74add1": "light blue", "#fdae61": "orange",
               "#762a83": "purple"}
    fig.suptitle(f"Time step {snap.step} (t = {result.world.times[snap.step]:.1f} s): green dashed = true target "
                 "box; " + " / ".join(colours.get(_COLORS[m], _COLORS[m]) for m in result.methods) + " = "
                 + " / ".join(LABELS[m] for m in result.methods) + " box at >= "
                 f"{result.pipeline.min_matches} matches", fontsize=9)
    return fig


def _discovery_clusters(result: ExperimentResult, n_landmarks: int = 6, n_target: int = 6):
    snap = result.snapshot
    R = len(result.world.references)
    ids = np.concatenate([np.full(len(f), k) for k, f in enumerate(snap.features)])
    labels = snap.labels
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(labels.max() + 2))
    clusters = [order[bounds[k]:bounds[k + 1]] for k in range(labels.max() + 1)]
    multi = [c for c in clusters if len(np.unique(ids[c])) >= 2]
    target = [c for c in multi if (ids[c] < R).any() and (ids[c] >= R).any()]
    landmarks = [c for c in multi if not (ids[c] < R).any()]
    landmarks.sort(key=lambda c: (-len(c), int(c[0])))
    target.sort(key=lambda c: (-int((ids[c] >= R).sum()), -len(c), int(c[0])))
    return ids, clusters, multi, landmarks[:n_landmarks], target[:n_target], target


def discovery_figure(result: ExperimentResult):
    snap = result.snapshot
    if snap is None:
        return None
    from matplotlib.patches import Rectangle

    ids, clusters, multi, landmarks, target_top, target = _discovery_clusters(result, n_landmarks=10)
    R = len(result.world.references)
    kp = np.vstack([f.keypoints for f in snap.features])
    n_img = len(snap.images)
    rows = 1 + int(math.ceil((n_img - R) / 3))
    fig = _figure(4.2 * 3, 3.2 * rows + 0.6)
    gs = fig.add_gridspec(rows, 3 * R)
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    colour = np.full(len(kp), -1)
    for k, c in enumerate(landmarks):
        colour[c] = k
    in_target = np.zeros(len(kp), bool)
    for c in target:
        in_target[c] = True
    for i in range(n_img):
        if i < R:
            ax = fig.add_subplot(gs[0, 3 * i:3 * i + 3])
        else:
            j = i - R
            ax = fig.add_subplot(gs[1 + j // 3, (j % 3) * R:(j % 3) * R + R])
        img = snap.images[i]
        ax.imshow(img, cmap="gray", vmin=0, vmax=255)
        mine = ids == i
        ax.plot(kp[mine, 0], kp[mine, 1], ".", ms=1.5, color="#ffff66", alpha=0.5)
        for k in range(len(landmarks)):
            s = mine & (colour == k)
            ax.plot(kp[s, 0], kp[s, 1], "s", ms=6, mfc="none", mec=cmap(k % 10), mew=1.6)
        s = mine & in_target
        ax.plot(kp[s, 0], kp[s, 1], "o", ms=5, mfc="none", mec="#ff2020", mew=1.4)
        if i >= R:
            tr = snap.truths[i - R]
            if tr.box is not None:
                x0, y0, x1, y1 = tr.box
                ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="#00c000", lw=1.2, ls="--"))
            ax.set_title(f"cam {i - R}: {int(s.sum())} features in target clusters", fontsize=8)
        else:
            ax.set_title(f"reference {i}: {int(s.sum())} in target clusters", fontsize=8)
        ax.set_xlim(0, img.shape[1])
        ax.set_ylim(img.shape[0], 0)
        ax.set_axis_off()
    sizes = np.array([len(c) for c in multi])
    fig.suptitle(
        f"Feature discovery at time step {snap.step}: QuickMatch (rho {result.pipeline.rho:g}) over "
        f"{R} references + {n_img - R} cameras: {len(multi)} clusters span 2+ images "
        f"(largest {sizes.max() if len(sizes) else 0}).\n"
        f"Squares: the {len(landmarks)} largest clusters without a reference feature (landmarks, one colour each); "
        f"red circles: the {len(target)} clusters joining a reference and a camera (the target); "
        "green dashed: true target", fontsize=9)
    return fig


def clusters_patches_figure(result: ExperimentResult):
    snap = result.snapshot
    if snap is None:
        return None
    ids, _, _, landmarks, target_top, _ = _discovery_clusters(result)
    chosen = landmarks + target_top
    if not chosen:
        return None
    kp = np.vstack([f.keypoints for f in snap.features])
    return clusters_figure(snap.images, kp, ids, chosen, radius=24, max_columns=9,
                           title=f"Time step {snap.step}: top rows = largest landmark clusters, "
                                 f"bottom {len(target_top)} rows = target clusters (reference image first)")


# --- markdown: several seeds and the comparison with the paper ---------------------------------

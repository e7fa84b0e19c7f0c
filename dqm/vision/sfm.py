"""Sparse reconstruction from dqm's tracks with pycolmap's mappers, and a figure of it.

Used by ``dqm sfm`` (images -> model in one command) and ``scripts/bench_sfm.py``.

Determinism: the mappers get a fixed random seed (:data:`DEFAULT_SEED`; COLMAP's default is
unseeded), so the same database gives the same model on one machine. COLMAP's mappers run
multi-threaded and their result can still depend on the number of threads (docs/sfm.md).
"""
from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from .. import signals
from ..progress import ProgressArg, resolve_progress, ticking
from ..validation import InputError
from .colmap import colmap_log_kept, require_pycolmap
from .features import COLMAP_MAX_FEATURES
from .triangulation import MIN_SHARED_POINTS, covisible_pairs

LOG = logging.getLogger("dqm.vision")

#: the mappers dqm sfm can run: COLMAP's incremental mapper (its default) and its global mapper (ex-GLOMAP)
MAPPERS = ("incremental", "global")
#: ``dqm sfm --mapper auto`` (its default) runs the global mapper from this many images on, the incremental one below
GLOBAL_FROM = 30


def choose_mapper(mapper: str, n_images: int) -> str:
    """The mapper ``dqm sfm`` runs: ``incremental`` or ``global`` as asked; ``auto``, the global mapper from
    :data:`GLOBAL_FROM` images on. Measured (docs/sfm.md): nerf_lego's 100 renders, where the incremental mapper
    registered a third of the views on the wrong side of the object for one verification seed in three (AUC@1
    0.28), the global one 0.58-0.66 for all three; dtu/scan24's 49 photos, AUC@1/2/5 0.507 / 0.753 / 0.901
    global against 0.496 / 0.747 / 0.899; strecha/entry-P10's 10 photos, 0.648 incremental against 0.628
    global. The threshold lies between the sets measured and was not tuned further."""
    if mapper == "auto":
        return "global" if n_images >= GLOBAL_FROM else "incremental"
    return mapper


#: ``dqm sfm --preset auto`` (its default): the SIFT preset of a collection below :data:`GLOBAL_FROM` images
SMALL_SCENE_PRESET = "budget"
#: ... and from there on
LARGE_SCENE_PRESET = "sfm"
#: ... with at most this many features an image (COLMAP's ``max_num_features``), unless --max-features says otherwise
LARGE_SCENE_MAX_FEATURES = COLMAP_MAX_FEATURES


def choose_features(preset: str, max_features: Optional[int], n_images: int) -> Tuple[str, int]:
    """The SIFT preset ``dqm sfm`` extracts with and its features an image at most (0: no limit).

    ``preset`` as asked, ``max_features`` as asked (``None``: not given, no limit). ``auto``: COLMAP's feature
    budget (:data:`SMALL_SCENE_PRESET`: contrast 0.02, each image's 8,192 strongest locations) below
    :data:`GLOBAL_FROM` images, where the incremental mapper runs and time is small; from there the ``sfm``
    preset (contrast 0.03) with each image's :data:`LARGE_SCENE_MAX_FEATURES` strongest features (COLMAP's
    ``max_num_features``), unless ``max_features`` is given. Measured (docs/sfm.md, "Where COLMAP's points go"
    and "dtu/scan24"): the budget gives entry-P10's 10 photos 1.23x the 3-D points at the same cameras (three
    seeds) and sacre_coeur's 10 photos 1.10x, but dtu/scan24's 49 photos 0.76x the points and nerf_lego's 100
    renders 1.45x the time; on dtu/scan24 (13,600 features an image without a cap) the cap takes QuickMatch,
    whose pair scan grows with the square of the features, from 169.8 to 64.3 s and the whole run from 0.76x
    to 0.43x COLMAP's time (one run beside it), at 0.62x the 3-D points (1.64x COLMAP's) and cameras within
    0.005 AUC (still above COLMAP's). nerf_lego's renders (at most 3,444 features an image) are not cut. The
    threshold is the mapper's (:func:`choose_mapper`) and was not tuned."""
    if preset != "auto":
        return preset, int(max_features or 0)
    if n_images < GLOBAL_FROM:
        return SMALL_SCENE_PRESET, int(max_features or 0)
    return LARGE_SCENE_PRESET, int(LARGE_SCENE_MAX_FEATURES if max_features is None else max_features)


#: the seed of every random choice in the mapping and the two-view verification
DEFAULT_SEED = 0


def mapper_options(mapper: str = "incremental", seed: int = DEFAULT_SEED, num_threads: int = -1,
                   structure_less: bool = False):
    """pycolmap's options of a mapper (COLMAP's defaults, but for the incremental mapper's structure-less
    fallback, off unless ``structure_less``) with the random seed set (-1: COLMAP's unseeded default) and its
    threads (-1: all cores; 1 gives the same model bit for bit); InputError for a bad name."""
    pycolmap = require_pycolmap()
    if mapper not in MAPPERS:
        raise InputError(f"--mapper {mapper}: use one of {', '.join(MAPPERS)}")
    if int(seed) != seed or seed < -1:
        raise InputError(f"--seed must be an integer >= 0, got {seed}")
    options = pycolmap.IncrementalPipelineOptions() if mapper == "incremental" else pycolmap.GlobalPipelineOptions()
    options.random_seed = int(seed)
    options.num_threads = int(num_threads)
    if hasattr(options, "structure_less_registration_fallback") and not structure_less:
        # COLMAP 4's incremental mapper tries an image it cannot register from 3-D points again from 2-D matches
        # alone: about 30 s an attempt where the image belongs to another scene (two generated scenes of 4 and 5
        # images: mapping 131 s with it, 0.8 s without, the same two models; nerf_lego: the same model)
        options.structure_less_registration_fallback = False
    return options


@dataclass
class Model:
    """One model of a mapping: pycolmap's Reconstruction, the mapper's key for it and its folder, the smaller
    models tried into it (:func:`join_small_models`: one dict each, ``joined`` true where it was) and those it
    repeats (:func:`drop_repeats`)."""

    key: int
    rec: object
    folder: Path
    joins: list = field(default_factory=list)
    #: the smaller models whose every image this one holds, left out (:func:`drop_repeats`): one dict each
    repeats: list = field(default_factory=list)


def reconstruct(database, image_dir, out_dir, *, mapper: str = "incremental", seed: int = DEFAULT_SEED,
                num_threads: int = -1, structure_less: bool = False, split: bool = True, join: bool = True,
                progress: ProgressArg = None) -> tuple[list[Model], float]:
    """Every model of pycolmap's mapping of ``database`` that holds a 3-D point, the largest first
    (:func:`by_size`; empty if none), and the mapping time in seconds. Models go to ``out_dir`` (``0``, ``1``,
    ...; a model without a point stays there, left out with a warning): a collection of several scenes gives one
    model per scene.

    ``mapper``: ``incremental`` (``pycolmap.incremental_mapping``) or ``global``
    (``pycolmap.global_mapping``, COLMAP 4's global mapper); ``seed``: the mapper's random seed. ``split``: a
    model whose images fall in groups that share (almost) no 3-D point is one model per group (:func:`split_scenes`; the
    global mapper places the scenes of a collection in one model where a few verified image pairs join them).
    ``join``: a smaller model whose images the mapper can register, all of them, into a larger model it shares
    many verified image pairs with is joined into it (:func:`join_small_models`; the global mapper left 3 to 9 of
    nerf_lego's renders in a model of their own in a mixed collection).
    ``progress`` (:data:`dqm.progress.ProgressArg`): the incremental mapper's registered images of the
    database's, ``progress(done, total)`` as each is registered (a model's first two at once); the global
    mapper reports none, so with ``True`` a terminal shows the time it has taken instead.
    """
    pycolmap = require_pycolmap()
    options = mapper_options(mapper, seed, num_threads, structure_less)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if mapper == "incremental":
        bar = resolve_progress(progress, "mapping", unit="images")
        callbacks = {} if bar is None else _registration_callbacks(bar, _count_images(database))
        try:
            recs = signals.interruptible(pycolmap.incremental_mapping, str(database), str(image_dir), str(out),
                                         options=options, **callbacks)
        finally:
            getattr(bar, "close", lambda: None)()
    else:
        with ticking(progress, "mapping (COLMAP's global mapper)"):
            recs = signals.interruptible(pycolmap.global_mapping, str(database), str(image_dir), str(out),
                                         options=options)
    models = [Model(k, recs[k], out / str(k)) for k in by_size(recs)]
    for m in models:
        if m.rec.num_points3D() == 0:  # COLMAP's incremental mapper left cmu_hotel's frames 54, 56 and 61
            # (--single-camera) in a model without one: registered images with no structure are no model
            LOG.warning("the mapper's model %s (%d images) has no 3-D point: left out", m.folder,
                        m.rec.num_reg_images())
    models = [m for m in models if m.rec.num_points3D() > 0]
    if split:
        models = split_scenes(models, out)
    if join:
        models = join_small_models(models, database, image_dir, seed=seed, num_threads=num_threads,
                                   progress=progress)
    return drop_repeats(models), time.perf_counter() - t0


def linked_names(rec, least: int = MIN_SHARED_POINTS) -> set[str]:
    """The registered images of a model (pycolmap's Reconstruction) that share ``least`` 3-D points or more with
    another of its images (:func:`scene_groups`: the others are held by chance points)."""
    return {rec.image(i).name for pair in covisible_pairs(rec, least) for i in pair}


def drop_repeats(models: list[Model]) -> list[Model]:
    """``models`` (largest first) less each model whose every registered image one larger model holds too, each
    joined there to another image by its 3-D points (:func:`linked_names`): it adds no image, and two poses of an
    image are one too many. COLMAP's incremental mapper can start a model from images another model has
    registered (sacre_coeur's 10 photos: a model of all 10 and one of 2 of them; cmu_hotel's frames with one
    camera, --mapper incremental: one of 101 and one of 2). An image the larger model holds by chance points only
    (another scene's photo placed there) keeps the smaller model. Such a model is recorded in the larger one's
    ``repeats`` (``model``: its key, ``images``: its registered images); its folder stays."""
    kept: list[Model] = []
    linked: dict[int, set[str]] = {}  # of each kept model, by its place in kept
    for m in models:
        names = registered_names(m.rec)
        holder = None
        for j, k in enumerate(kept):
            if j not in linked:
                linked[j] = linked_names(k.rec)
            if names <= linked[j]:
                holder = k
                break
        if holder is None:
            kept.append(m)
            continue
        holder.repeats.append({"model": m.key, "images": len(names)})
        LOG.info("model %s (%d images) left out: each of its images is in model %s", m.folder, len(names),
                 holder.folder)
    return kept


def _count_images(database) -> int:
    """The images of a COLMAP database file."""
    pycolmap = require_pycolmap()
    db = pycolmap.Database.open(str(database))
    try:
        return int(db.num_images())
    finally:
        db.close()


def _registration_callbacks(bar, total: int) -> dict:
    """The incremental mapper's callbacks that count its registered images into ``bar(done, total)``: two for a
    model's first pair, one for each image after (capped at ``total``: an image registered again after it was
    dropped counts twice; a count that does not change is not reported)."""
    done = [0]

    def registered(k: int) -> None:
        now = min(total, done[0] + k)
        if now != done[0]:
            done[0] = now
            bar(now, total)

    return {"initial_image_pair_callback": lambda: registered(2), "next_image_callback": lambda: registered(1)}


def clusters_across(labels, group) -> np.ndarray:
    """The cluster labels whose members lie in two groups or more (``group``: every feature's group, e.g. its
    image's model or scene; negative: in none, left out), sorted."""
    labels, group = np.asarray(labels), np.asarray(group)
    on = group >= 0
    pairs = np.unique(np.stack([labels[on], group[on]], axis=1), axis=0)
    lab, n_groups = np.unique(pairs[:, 0], return_counts=True)
    return lab[n_groups > 1]


def scene_groups(rec, least: int = MIN_SHARED_POINTS) -> list[list[int]]:
    """The registered images of a model (pycolmap's Reconstruction) in the groups that hold together by the 3-D
    points they share (two images linked where they share ``least`` or more, the least the triangulation stage
    asks of an image pair it matches: chance matches between two scenes give a few points seen from both),
    largest first; an image linked to none joins the largest group. One group where the model is one scene."""
    ids = sorted(rec.reg_image_ids())
    parent = {i: i for i in ids}

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in covisible_pairs(rec, least):
        if root(a) != root(b):
            parent[root(b)] = root(a)
    groups: dict[int, list[int]] = {}
    for i in ids:
        groups.setdefault(root(i), []).append(i)
    many = sorted((g for g in groups.values() if len(g) > 1), key=lambda g: (-len(g), g[0]))
    if len(many) < 2:
        return [ids]
    many[0] = sorted(many[0] + [g[0] for g in groups.values() if len(g) == 1])
    return many


def linked_across(rec, groups: list[set[str]], least: int = MIN_SHARED_POINTS) -> bool:
    """Whether two registered images of a model (pycolmap's Reconstruction) that lie in two of ``groups`` (sets of
    image names; a name in several counts in the first) share ``least`` 3-D points or more: the model holds the
    groups together by its structure, not by chance points (:func:`scene_groups`)."""
    group_of: dict[str, int] = {}
    for g, names in enumerate(groups):
        for name in names:
            group_of.setdefault(name, g)
    where = {i: group_of.get(rec.image(i).name, -1) for i in rec.reg_image_ids()}
    return any(where[a] >= 0 and where[b] >= 0 and where[a] != where[b] for a, b in covisible_pairs(rec, least))


def split_scenes(models: list[Model], out: Path) -> list[Model]:
    """Each model whose images fall in groups that share (almost) no 3-D point (:func:`scene_groups`) as one model
    per group, written to ``out``: the largest group keeps the model's key and folder, the others take the next free
    keys. COLMAP 4's global mapper placed three scenes of a mixed collection (nerf_lego, entry-P10, sacre_coeur)
    in one model, joined by 6 verified image pairs and no point: their relative placement means nothing. The
    largest first (:func:`by_size`)."""
    pycolmap = require_pycolmap()
    key = max((m.key for m in models), default=-1) + 1
    result = []
    for m in models:
        groups = scene_groups(m.rec)
        if len(groups) == 1:
            result.append(m)
            continue
        LOG.info("model %d: %d groups of images (%s) that share almost no 3-D point, each a model of its own", m.key,
                 len(groups), ", ".join(str(len(g)) for g in groups))
        for k, group in enumerate(groups):
            rec = pycolmap.Reconstruction(m.rec)
            keep = set(group)
            for image_id in [i for i in rec.reg_image_ids() if i not in keep]:
                rec.deregister_frame(rec.image(image_id).frame_id)
            if k:
                folder, key = out / str(key), key + 1
            else:
                folder = m.folder
            folder.mkdir(parents=True, exist_ok=True)
            rec.write(str(folder))
            result.append(Model(int(folder.name), rec, folder))
    recs = {i: r.rec for i, r in enumerate(result)}
    return [result[i] for i in by_size(recs)]


#: :func:`join_small_models` tries a model with a larger one where their images make at least this many verified
#: image pairs for each image of the smaller model
JOIN_PAIRS_PER_IMAGE = 1


def verified_name_pairs(database) -> list[tuple[str, str, int]]:
    """The verified image pairs of the database file ``database`` by image name, with their inliers
    (:func:`dqm.vision.colmap.verified_pairs`)."""
    pycolmap = require_pycolmap()
    from .colmap import verified_pairs

    db = pycolmap.Database.open(str(database))
    try:
        name = {image.image_id: image.name for image in db.read_all_images()}
        return [(name[a], name[b], n) for a, b, n in verified_pairs(db)]
    finally:
        db.close()


def model_links(verified: list[tuple[str, str, int]], models: list[Model]) -> tuple[np.ndarray, np.ndarray]:
    """The verified image pairs (:func:`verified_name_pairs`) between the registered images of each two models of
    ``models``, and their inliers: two symmetric matrices, one row a model (the diagonal: each model's own
    pairs). An image registered in several models (COLMAP's incremental mapper can start a model from images
    another model holds) counts in the first of them only."""
    owner: dict[str, int] = {}
    for k, m in enumerate(models):
        for name in registered_names(m.rec):
            owner.setdefault(name, k)
    pairs = np.zeros((len(models), len(models)), np.int64)
    shared = np.zeros_like(pairs)
    for name_a, name_b, n in verified:
        a, b = owner.get(name_a, -1), owner.get(name_b, -1)
        if a >= 0 and b >= 0:
            for i, j in {(a, b), (b, a)}:
                pairs[i, j] += 1
                shared[i, j] += n
    return pairs, shared


def registered_names(rec) -> set[str]:
    """The names of a model's registered images (pycolmap's Reconstruction)."""
    return {rec.image(i).name for i in rec.reg_image_ids()}


def join_small_models(models: list[Model], database, image_dir, *, seed: int = DEFAULT_SEED, num_threads: int = -1,
                      progress: ProgressArg = None) -> list[Model]:
    """Each model, the smallest first, continued into the larger model it shares the most verified inliers with
    (where their images make at least :data:`JOIN_PAIRS_PER_IMAGE` verified pairs an image of the smaller): COLMAP's
    incremental mapper starts from the larger model (``input_path``) and registers the smaller one's images from
    the 3-D points they see. The result replaces the larger model (written to its folder; the smaller one's
    folder is removed) only where every image of both is registered and the images still hold together by their
    3-D points (:func:`scene_groups`: one group); else both stay as they were. Each try is recorded in the
    larger model's ``joins``. A model whose images all lie in a larger model too has no pair of its own
    (:func:`model_links`) and is left as it is. The largest first (:func:`by_size`).

    Why: COLMAP 4's global mapper left 3 (another folder order: 9) of nerf_lego's 100 renders in a model of their
    own in the mixed collection of docs/sfm.md (165 verified pairs with the other 91, 4,621 inliers); continuing
    the 91's model registered all 9 in 11.6 s. Images of two scenes make few verified pairs (3 pairs between
    entry-P10's and sacre_coeur's 10 photos there), and an image that COLMAP cannot place from 30 inlier
    correspondences of the larger model is not registered, so scenes are not joined."""
    pycolmap = require_pycolmap()
    models = list(models)
    verified = verified_name_pairs(database) if len(models) > 1 else []
    for small in sorted(models, key=lambda m: (m.rec.num_reg_images(), m.rec.num_points3D(), -m.key)):
        s = next((k for k, m in enumerate(models) if m is small), None)
        if s is None or len(models) < 2:  # joined into another already
            continue
        pairs, shared = model_links(verified, models)
        n = small.rec.num_reg_images()
        larger = [k for k, m in enumerate(models) if k != s and m.rec.num_reg_images() >= n and
                  pairs[s, k] >= JOIN_PAIRS_PER_IMAGE * n]
        if not larger:
            continue
        b = max(larger, key=lambda k: (shared[s, k], -k))
        big = models[b]
        names = registered_names(big.rec) | registered_names(small.rec)
        options = mapper_options("incremental", seed, num_threads)
        options.image_names = sorted(names)
        options.multiple_models = False
        work = big.folder.parent / f".joining-{small.key}-into-{big.key}"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        t0 = time.perf_counter()
        try:
            with ticking(progress, f"registering {n} images of model {small.key} into model {big.key}"):
                recs = signals.interruptible(pycolmap.incremental_mapping, str(database), str(image_dir), str(work),
                                             options=options, input_path=str(big.folder))
            rec = recs[largest(recs)] if recs else None
        finally:
            shutil.rmtree(work, ignore_errors=True)
        now = registered_names(rec) if rec is not None else set()
        got, kept = len(now & registered_names(small.rec)), len(now & registered_names(big.rec))
        whole = got == n and kept == big.rec.num_reg_images() and len(scene_groups(rec)) == 1
        entry = {"model": small.key, "images": n, "registered": got, "larger_kept": kept, "joined": whole,
                 "pairs": int(pairs[s, b]), "seconds": round(time.perf_counter() - t0, 2)}
        LOG.info("model %d (%d images) into model %d: %d of them registered, %d of its %d kept: %s", small.key, n,
                 big.key, got, kept, big.rec.num_reg_images(), "joined" if whole else "kept apart")
        if whole:
            rec.write(str(big.folder))
            shutil.rmtree(small.folder, ignore_errors=True)
            big.rec = rec
            del models[s]
        big.joins.append(entry)
    recs = {k: m.rec for k, m in enumerate(models)}
    return [models[k] for k in by_size(recs)]


def by_size(recs: dict) -> list[int]:
    """The models' keys, largest first: most registered images, then most points, then the lowest key."""
    return sorted(recs, key=lambda k: (-recs[k].num_reg_images(), -recs[k].num_points3D(), k))


def largest(recs: dict) -> int:
    """The key of the largest model (:func:`by_size`'s first)."""
    return by_size(recs)[0]


def bogus_cameras(rec) -> list[str]:
    """The names of a model's registered images whose camera COLMAP calls bogus (``Camera.has_bogus_params``): a
    focal length outside 0.1-10x the larger image side or an extra parameter (a distortion coefficient) beyond
    +-1, the bounds of pycolmap's ``IncrementalMapperOptions``. Its incremental mapper drops such an image from a
    model; its global mapper keeps them: on cmu_hotel's video frames, a camera a frame, it estimated a radial
    distortion k of -3 to -4 for every frame (pixels more than 290-330 px from the centre of a 512 px frame then
    have no undistorted position)."""
    pycolmap = require_pycolmap()
    bounds = pycolmap.IncrementalMapperOptions()
    return sorted(rec.image(i).name for i in rec.reg_image_ids()
                  if rec.cameras[rec.image(i).camera_id].has_bogus_params(
                      bounds.min_focal_length_ratio, bounds.max_focal_length_ratio, bounds.max_extra_param))


def model_numbers(rec) -> dict:
    """Registered images, 3-D points, mean track length, mean reprojection error (px) and the registered images
    with a bogus camera (:func:`bogus_cameras`) of a model."""
    if rec is None:
        return {"registered": 0, "points": 0, "track": float("nan"), "reproj": float("nan"), "bogus_cameras": 0}
    return {"registered": rec.num_reg_images(), "points": rec.num_points3D(),
            "track": rec.compute_mean_track_length(), "reproj": rec.compute_mean_reprojection_error(),
            "bogus_cameras": len(bogus_cameras(rec))}


def model_figure(rec, path, title: str) -> None:
    """A sparse model from the front (the points' two main axes) and from above (main and depth axes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    C = np.array([im.projection_center() for im in rec.images.values() if im.has_pose]).reshape(-1, 3)
    # the axes and the extent of the points; of the cameras too where there are fewer than three points (COLMAP's
    # incremental mapper left three of cmu_hotel's frames in a model with none)
    basis = P if len(P) >= 3 else np.vstack([P, C])
    centre = np.median(basis, axis=0) if len(basis) else np.zeros(3)
    vt = np.linalg.svd(basis - centre, full_matrices=len(basis) < 3)[2] if len(basis) else np.eye(3)
    p3, c3 = (P - centre) @ vt.T, (C - centre) @ vt.T
    lim = (np.percentile(np.abs((basis - centre) @ vt.T), 98, axis=0) if len(basis) else np.ones(3)) * 1.2 + 1e-12
    fig, (front, top) = plt.subplots(1, 2, figsize=(11, 5), dpi=110)
    # points as one line's markers, the legend under the axes and fixed margins: half the time of scattered
    # points, a legend placed by searching the data and a layout found by drawing the figure twice (0.2 against
    # 0.4 s of CPU for 8,000 points on a 2-core AMD EPYC)
    dots = dict(linestyle="none", marker=".", markersize=1.6, markeredgewidth=0, color="#4575b4", alpha=0.7)
    front.plot(p3[:, 0], p3[:, 1], **dots)
    front.set_xlim(-lim[0], lim[0])
    front.set_ylim(-lim[1], lim[1])
    front.set_title(f"front: {len(P):,} 3-D points")
    top.plot(p3[:, 0], p3[:, 2], label="3-D points", **dots)
    top.scatter(c3[:, 0], c3[:, 2], s=45, c="#d73027", marker="^", label=f"{len(C)} cameras")
    top.set_title("from above, with the cameras")
    legend = fig.legend(loc="lower right", ncol=2, frameon=False)
    legend.legend_handles[0].set_markersize(6)
    for ax, yl in ((front, "main axis 2"), (top, "depth axis")):
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("main axis 1 (model units)")
        ax.set_ylabel(yl)
    fig.suptitle(title)
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.16, top=0.86, wspace=0.25)
    fig.savefig(path)
    plt.close(fig)


def colmap_pipeline(image_dir, work_dir, *, seed: int | None = None, mapper: str = "incremental",
                    single_camera: bool = False):
    """COLMAP's own pipeline on an image folder, as a user runs it through pycolmap with its defaults:
    its SIFT (``extract_features``), exhaustive matching with its verification (``match_exhaustive``)
    and a mapper; the peer of ``dqm sfm`` in ``scripts/bench_sfm.py``.

    ``seed`` None keeps COLMAP's unseeded defaults; a number seeds its verification and mapper.
    ``single_camera``: one camera for every image (COLMAP's ``CameraMode.SINGLE``, ``dqm sfm --single-camera``).
    Returns every model, the largest first (:class:`Model`; none if the mapper made none), and the seconds of
    each stage (extract, match, map).
    """
    pycolmap = require_pycolmap()
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    database = work / "database.db"
    times = {}
    t0 = time.perf_counter()
    with colmap_log_kept(pycolmap, pycolmap.logging.ERROR):  # its warning that the extraction uses every core
        mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO
        signals.interruptible(pycolmap.extract_features, str(database), str(image_dir), camera_mode=mode)
    times["extract"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    two_view = pycolmap.TwoViewGeometryOptions()
    if seed is not None:
        two_view.ransac.random_seed = int(seed)
    signals.interruptible(pycolmap.match_exhaustive, str(database), verification_options=two_view)
    times["match"] = time.perf_counter() - t0
    models, times["map"] = reconstruct(database, image_dir, work / "sparse", mapper=mapper,
                                       seed=-1 if seed is None else seed, structure_less=True, split=False)
    return models, times

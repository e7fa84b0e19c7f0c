"""Images to a sparse 3-D model in one command: SIFT, QuickMatch, COLMAP export, pycolmap's mapper,
a figure of the model and, with --gt, its cameras against ground truth.

    dqm sfm photos/ --out model/
    dqm sfm photos/ --out model/ --gt gt_cameras/        # + pose errors and AUC (Strecha files or a COLMAP model)
    dqm sfm photos/ --out model/ --preset colmap --camera-model OPENCV --single-camera
    dqm sfm --clusters model/clusters.npz --out model2/  # from a run's clusters: no SIFT, no QuickMatch

MODEL_DIR (new or empty) receives clusters.npz (dqm's CLUSTERS file), database.db (the COLMAP
database: cameras, keypoints, the clusters' matches, verified geometries), sparse/0 ... (the
models the mapper made, in COLMAP's binary format), model.png (the largest model from the
front and from above), tracks.csv and sfm.json (the stage times, the model's numbers and, with
--gt, the pose scores). In a collection of several scenes and 30 images or more, a scene whose
model holds fewer than 30 is made again from its images alone, with the choices --preset auto and
--mapper auto make for its size (scenes/<k>/: its clusters, database and model). Where --mapper auto's
global mapper makes no model, the incremental mapper runs on the same database. Where a model has
cameras COLMAP calls bogus (a focal length or a distortion out of its bounds, as a camera a frame of a
video can get) and its images, a camera each, have one size a folder and no EXIF focal length, they are
mapped again with one camera per folder (shared-camera/<k>/), which replaces the model where it
registers as many images with fewer bogus cameras and as many 3-D points (the cameras are looked at after the
mapper and again after the last stage, whose bundle adjustment can leave them bogus; images mapped again with
the run's SIFT choice take their features from the run's, and every image its clusters too). With --clusters
FILE (a run's clusters.npz, or dqm match's on images) the run starts from its features and clusters: no
extraction or matching of them, the later stages choosing as the file's run did. It is the chain
`dqm match` -> `dqm export colmap` -> pycolmap's mapper with the same options (docs/sfm.md). Every
random choice is seeded (--seed): the same photos and options give the same model. Needs pycolmap:
pip install 'dqm[colmap]'.
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import shutil
import sys
import time
from pathlib import Path

from .. import io, outputs
from ..validation import InputError
from ..wording import count
from .export import add_camera_sharing_options, add_cluster_matches_option, camera_sharing
from .extract import add_image_options, extract
from .match import add_cluster_options, cluster

LOG = logging.getLogger("dqm.commands")

NAME = "sfm"
HELP = "images -> sparse 3-D model (extract, QuickMatch, export to COLMAP, pycolmap mapping; --gt: pose accuracy)"


def add_arguments(p) -> None:
    from ..vision.colmap import SFM_PARTNERS
    from ..vision.sfm import (
        DEFAULT_SEED,
        GLOBAL_FROM,
        LARGE_SCENE_MAX_FEATURES,
        LARGE_SCENE_PRESET,
        MAPPERS,
        SMALL_SCENE_PRESET,
    )

    p.add_argument("inputs", nargs="*", metavar="IMAGES",
                   help="image folders / globs / files (or none, with --image-list)")
    p.add_argument("--out", required=True, metavar="MODEL_DIR", help="folder to create (or an empty one)")
    p.add_argument("--clusters", default=None, metavar="CLUSTERS",
                   help="start from a CLUSTERS file instead of images (a dqm sfm run's clusters.npz, or dqm match's "
                        "on images): its features and clusters go to the export, the mapper and the last stage, "
                        "with no extraction or matching; its images are read where it names them. To go on where a "
                        "run stopped, or to map again with other options")
    p.add_argument("--image-dir", default=None, metavar="DIR",
                   help="with --clusters: the folder its images are in now, if they moved since (another host's "
                        "paths in a distributed job's file): each found as named, else under DIR by its name")
    p.add_argument("--features", default=None, nargs="+", metavar="FEATURES",
                   help="with --clusters of a distributed job (dqm run, dqm coordinator: the descriptors stay with "
                        "the agents): the FEATURES file the job ran on, or its agents' files (with feature_ids, "
                        "as dqm split writes them; a file without them as AGENT=FILE[,FILE...], the agent that "
                        "held it), whose descriptors the last stage matches (without it, --no-triangulate maps the "
                        "file's clusters alone)")
    before = {action.dest for action in p._actions}
    add_image_options(p, default_preset="auto",
                      auto=f"{SMALL_SCENE_PRESET} below {GLOBAL_FROM} images (more 3-D points where time is small), "
                           f"{LARGE_SCENE_PRESET} with each image's {LARGE_SCENE_MAX_FEATURES:,} strongest features "
                           f"(COLMAP's budget) from there (a scene of fewer in a larger collection is matched "
                           f"again alone with {SMALL_SCENE_PRESET}; docs/sfm.md)",
                      auto_max_features=f"{LARGE_SCENE_MAX_FEATURES:,} (COLMAP's) where --preset auto takes "
                                        f"{LARGE_SCENE_PRESET} ({GLOBAL_FROM} images or more: QuickMatch's time grows "
                                        f"with the square of the features), else no limit")
    add_cluster_options(p, "sfm")
    # the options of the extraction and the matching, as those two helpers define them: refused with --clusters,
    # whose file made both (the threads and the memory budget are not choices of the result: they stay)
    matching = [action.dest for action in p._actions if action.dest not in before | _RESOURCES]
    p.add_argument("--camera-model", default=None, metavar="MODEL",
                   help="COLMAP camera model of every camera (default SIMPLE_RADIAL, as COLMAP's)")
    add_camera_sharing_options(p)
    add_cluster_matches_option(p)
    p.add_argument("--mapper", choices=("auto",) + MAPPERS, default="auto",
                   help=f"COLMAP's incremental mapper or its global mapper (COLMAP 4, ex-GLOMAP); auto (default): the "
                        f"global one from {GLOBAL_FROM} images (the incremental one where it makes no model), the "
                        f"incremental one below (docs/sfm.md)")
    p.add_argument("--partners", type=int, default=SFM_PARTNERS, metavar="N",
                   help=f"verify and map each image's N image pairs with the most shared clusters (and the pairs "
                        f"where it is among the other image's N): the pairs grow with the images, not with their "
                        f"pairs (default {SFM_PARTNERS}: every pair below {SFM_PARTNERS + 2} images; 0: every pair)")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED,
                   help=f"random seed of the two-view verification and the mapper (default {DEFAULT_SEED})")
    p.add_argument("--mapper-threads", type=int, default=1, metavar="N",
                   help="threads of the mapper (default 1: the same model bit for bit on every run; 0: all cores, "
                        "faster on large jobs, the model then varies in its last digits)")
    p.add_argument("--triangulate", action=argparse.BooleanOptionalAction, default=True,
                   help="after mapping, match each image with the 8 that share the most points with it under the "
                        "model's own geometry (0.5 px of its epipolar lines, mutual nearest descriptors, ratio 0.8) "
                        "and triangulate with the cameras fixed: more 3-D points (default; --no-triangulate: the "
                        "mapper's model as it is)")
    p.add_argument("--bundle-adjust", action=argparse.BooleanOptionalAction, default=True,
                   help="after the triangulation, adjust the whole model once with COLMAP's bundle adjuster (poses, "
                        "points, focal lengths, distortion): better cameras on every scene measured (default; "
                        "--no-bundle-adjust: the mapper's cameras bit for bit)")
    p.add_argument("--gt", default=None, metavar="DIR",
                   help="ground-truth cameras (a folder of Strecha *.camera files, or a COLMAP model): print the "
                        "model's pose errors and pairwise pose AUC@1/2/5 degrees (docs/sfm.md)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(matching_defaults={dest: p.get_default(dest) for dest in matching})


#: options of the matching that change how it runs, not what it gives: kept with --clusters (images matched again)
_RESOURCES = {"threads", "max_memory"}


def _from_clusters(args):
    """``--clusters FILE``: its features, its clusters (as QuickMatch's result: the labels) and the choices it was
    made with, checked before any work: every option of the extraction or the matching is refused (the file's
    stand: its QuickMatch parameters and geometric steps are set on ``args`` for any images matched again), the
    arrays the stages need must be there, and the clusters must hold at most one feature of an image each."""
    import types

    import numpy as np

    where = f"--clusters {args.clusters}"
    if args.inputs or args.image_list:
        raise InputError(f"{where} holds the features and the clusters; give images or --clusters, not both")
    given = [dest for dest, default in args.matching_defaults.items() if getattr(args, dest) != default]
    if given:
        raise InputError(f"--{given[0].replace('_', '-')} is a choice of the extraction or the matching; {where} "
                         "made both (give images instead to choose them)")
    c = io.load_clusters(args.clusters)
    for key in ("keypoints", "image_names"):
        if key not in c:
            raise InputError(f"{where}: no {key!r} array; dqm sfm needs the features' keypoints and images (match "
                             "images with dqm match or dqm sfm)")
    fs = io.FeatureSet(descriptors=np.zeros((len(c["labels"]), 1), np.uint8), image_ids=c["image_ids"],
                       **{name: c.get(name) for name in io.OPTIONAL_FIELDS}).validate(where)
    if "descriptors" in c:
        if args.features is not None:
            raise InputError(f"--features {args.features[0]}: {where} holds its descriptors already")
        fs.descriptors = c["descriptors"]
        fs.validate(where)
    elif args.features is not None:
        fs.descriptors = _descriptors_of(args.features, fs, where)
    elif args.triangulate:
        raise InputError(f"{where} has no descriptors (a distributed job's file: they stay with the agents), and the "
                         "last stage matches them: give --features, the FEATURES file the job ran on, or "
                         "--no-triangulate for the mapper's model of its clusters")
    else:  # the export and the mapper need none; nothing is matched again (_map_again_per_folder)
        fs.descriptors = np.zeros((len(fs), 0), np.uint8)
    labels = np.asarray(c["labels"])
    if labels.shape != (len(fs),) or labels.dtype.kind not in "iu":
        raise InputError(f"{where}: labels must be one integer per feature ({len(fs)}), got {labels.dtype} "
                         f"{labels.shape}")
    io.check_one_feature_an_image(labels, fs.image_ids, fs.image_names, where, "dqm sfm")
    if args.image_dir is not None and not Path(args.image_dir).is_dir():
        raise InputError(f"--image-dir {args.image_dir}: no such folder")
    found = [io.find_image(str(name), args.image_dir) for name in fs.image_names]
    if None in found:
        missing = fs.image_names[found.index(None)]
        where_else = f" nor under --image-dir {args.image_dir}" if args.image_dir else " (--image-dir: where it is now)"
        raise InputError(f"{where} names image {missing}, which is not there{where_else}")
    found = [p.resolve() for p in found]
    if len(set(found)) < len(found):
        twice = next(p for p in found if found.count(p) > 1)
        a, b = [str(fs.image_names[k]) for k, p in enumerate(found) if p == twice][:2]
        raise InputError(f"{where}: images {a} and {b} are both found as {twice}; give the folder they are in now "
                         "with their own names")
    fs.image_names = np.array([str(p) for p in found])  # where they are now: the export and the stages read them
    params = c["params"]
    for dest in ("rho", "ratio_density", "kernel", "parent"):
        if dest in params:
            setattr(args, dest, params[dest])
    args.guided, args.verify = bool(params.get("guided")), bool(params.get("verify"))
    args.preset, args.max_features = params.get("preset"), params.get("max_features")
    asked = "asked_preset" in params
    args.asked_preset = params["asked_preset"] if asked else args.preset
    args.asked_max_features = params.get("asked_max_features") if asked else args.max_features
    extra = {key: params[key] for key in ("verify", "guided") if key in params} or None
    return fs, types.SimpleNamespace(labels=labels.astype(np.int64)), extra


def _feature_files(specs: "list[str]") -> "list[tuple]":
    """``--features``' specs as ``(agent, [paths])``: ``FILE`` (agent None) or ``AGENT=FILE[,FILE...]``, the files
    an agent of the job held (as ``dqm agent --peer-features`` names them)."""
    from ..distributed.sources import agent_files

    return [agent_files(spec, "--features") if spec.partition("=")[0].strip().isdigit() and "=" in spec
            else (None, [spec]) for spec in specs]


def _descriptors_of(specs: "list[str]", fs: io.FeatureSet, where: str):
    """The descriptors of the features of ``fs`` (a distributed job's CLUSTERS file: rows by feature id) in the
    FEATURES files ``specs`` names (:func:`_feature_files`) as the job numbered them: a file's ``feature_ids``;
    without them, the rows of a file given alone, or ``(agent << 32) + row`` over the files of an agent given
    as ``AGENT=FILE[,FILE...]`` (as its agent process numbered them). Checked to be those features: no id twice,
    every id present, the same keypoints."""
    import numpy as np

    from ..distributed.sources import IMAGE_BITS, feature_ids

    groups = [(agent, [(path, io.load_features(path)) for path in paths]) for agent, paths in _feature_files(specs)]
    files = [item for _, loaded in groups for item in loaded]
    named = " ".join(specs)
    if len(files) > 1:
        bare = next((path for agent, loaded in groups for path, f in loaded
                     if agent is None and f.feature_ids is None), None)
        if bare is not None:
            raise InputError(f"--features {bare}: no feature_ids array, so the job numbered its features by the "
                             f"agent that held it: give it as AGENT={bare}")
        dims = sorted({f.descriptors.shape[1] for _, f in files})
        if len(dims) > 1:
            raise InputError(f"--features {named}: descriptors of different dimensions ({dims})")
    bare = next((path for path, f in files if f.keypoints is None), None)
    if bare is not None:
        raise InputError(f"--features {bare}: no keypoints, so its features cannot be checked against {where}'s")
    parts = []
    for agent, loaded in groups:
        sets = [f for _, f in loaded]
        parts.append(sets[0].global_ids() if agent is None else feature_ids(sets, agent))
    ids = np.concatenate(parts)
    order = np.argsort(ids, kind="stable")
    repeated = np.flatnonzero(ids[order][1:] == ids[order][:-1])
    if len(repeated):
        raise InputError(f"--features {named}: feature id {int(ids[order][repeated[0]])} is there twice (give "
                         "each file once, each agent's under its own number)")
    wanted = fs.global_ids()
    rows = order[np.minimum(np.searchsorted(ids, wanted, sorter=order), max(len(ids) - 1, 0))] if len(ids) else None
    absent = np.flatnonzero(ids[rows] != wanted) if len(ids) else np.arange(len(wanted))
    if len(absent):
        first = int(wanted[absent[0]])
        agent = first >> IMAGE_BITS
        fix = (f"agent {agent} numbered it (its row {first - (agent << IMAGE_BITS)}): give that agent's files as "
               f"{agent}=FILE[,FILE...]" if agent else "give the FEATURES file the job ran on, or every agent's files")
        raise InputError(f"--features {named}: feature {first} of {where} is not there; {fix}")
    keypoints = np.concatenate([np.asarray(f.keypoints)[:, :2] for _, f in files])
    if not np.array_equal(keypoints[rows], np.asarray(fs.keypoints)[:, :2]):
        raise InputError(f"--features {named}: the keypoints are not those of {where}'s features (give the "
                         "FEATURES files the job ran on)")
    return np.concatenate([f.descriptors for _, f in files])[rows]


def _triangulate(rec, database: Path, export, fs, folder: Path, seed: int, mapper_threads: int, threads,
                 bundle_adjust: bool, progress: bool):
    """The model with the points that matches under its own geometry add (:mod:`dqm.vision.triangulation`),
    written over the mapper's model in ``folder``."""
    import numpy as np

    from ..vision.triangulation import triangulate

    by_name = {name: k for k, name in enumerate(export.names)}
    keypoints, descriptors = {}, {}
    for image_id, image in rec.images.items():
        if image.has_pose:
            rows = np.flatnonzero(fs.image_ids == by_name[image.name])
            keypoints[image_id], descriptors[image_id] = fs.keypoints[rows, :2], fs.descriptors[rows]
    return triangulate(rec, database, export.image_dir, folder, keypoints, descriptors, seed=seed,
                       num_threads=mapper_threads, n_threads=threads, bundle_adjust=bundle_adjust, progress=progress)


def _out_dir(path: str) -> Path:
    """MODEL_DIR checked before any work: absent (created) or an empty folder; never overwritten."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file; dqm sfm writes a folder")
    if out.is_dir() and any(out.iterdir()):
        raise InputError(f"--out {out} is not empty; dqm sfm writes into a new or empty folder")
    return outputs.check_dir(out, "--out")  # probed for writing; created when the first file is written


class _Stages:
    """Each stage's seconds and the process's peak resident memory while it ran (the peak restarted at its
    start: :func:`dqm.core.memory.restart_peak`)."""

    def __init__(self):
        self.times: dict[str, float] = {}
        self.peaks: dict[str, int] = {}

    @contextlib.contextmanager
    def __call__(self, name: str):
        from ..core import memory

        memory.restart_peak()
        t = time.perf_counter()
        try:
            yield
        finally:
            self.times[name] = self.times.get(name, 0.0) + time.perf_counter() - t
            self.peaks[name] = max(self.peaks.get(name, 0), memory.peak_bytes())

    def line(self) -> str:
        from ..core.memory import format_bytes

        return "times (peak memory): " + ", ".join(
            f"{name} {t:.1f} s ({format_bytes(self.peaks[name])})" for name, t in self.times.items())


def _folder(model, out: Path) -> str:
    """A model's folder as sfm.json and the summary name it: relative to MODEL_DIR, '/'-separated."""
    return model.folder.relative_to(out).as_posix()


def _match_and_map(args, out: Path, stage: _Stages, camera, threads: int, image_dir=None, say: str = "",
                   features=None, clusters=None):
    """The stages before the triangulation on the images ``args`` names, written into ``out``: SIFT, QuickMatch,
    clusters.npz, tracks.csv and database.db (image names relative to ``image_dir``, default the images' common
    folder), and the mapper's models in ``out/sparse``. ``features``: these images' features, made before (no
    extraction); ``clusters``: QuickMatch's result and extras on them, made before (no matching, and no
    clusters.npz or tracks.csv: they are written where they were made). Returns the features, QuickMatch's
    result and extras, the export's summary, the mapper chosen and the models (largest first)."""
    from ..vision import colmap
    from ..vision.sfm import choose_mapper, reconstruct

    if features is None:
        with stage("extract"):
            fs = extract(args, min_images=2)
    else:
        fs = features
    if clusters is None:
        with stage("match"):
            result, extra = cluster(args, fs)
    else:
        result, extra = clusters
    with stage("export"):
        if clusters is None:  # with the SIFT choice and what was asked, for a run that starts from it (--clusters)
            io.save_clusters(out / "clusters.npz", fs, result,
                             dict(extra or {}, preset=args.preset, max_features=args.max_features,
                                  asked_preset=args.asked_preset, asked_max_features=args.asked_max_features))
            io.save_tracks_csv(out / "tracks.csv", result.labels, fs.image_ids, fs.keypoints, fs.image_names)
        paths = colmap.resolve_images(fs.image_names, None)
        s = colmap.export_database(out / "database.db", fs.keypoints, fs.image_ids, paths, result.labels,
                                   image_dir=image_dir, descriptors=fs.descriptors, camera=camera, seed=args.seed,
                                   partners=args.partners, cluster_matches=args.cluster_matches,
                                   progress=not args.quiet)
    mapper = choose_mapper(args.mapper, s.n_images)
    print(f"{say}wrote {out / 'database.db'}: {s.n_images} images, {s.pairs_line()}, {s.verified_line()}; "
          f"{mapper} mapping ...", flush=True)
    with stage("map"):
        models, seconds = reconstruct(out / "database.db", s.image_dir, out / "sparse", mapper=mapper,
                                      seed=args.seed, num_threads=threads, progress=not args.quiet)
        if not models and mapper == "global" and args.mapper == "auto":
            # the global mapper's chosen, not asked for: where it makes no model, the incremental one may (cmu_hotel's
            # 101 video frames with --single-camera: no model on one thread, 101 frames on two; the incremental
            # mapper registered all 101)
            mapper = "incremental"
            print(f"{say}COLMAP's global mapper made no model ({seconds:.1f} s); {mapper} mapping instead ...",
                  flush=True)
            models, _ = reconstruct(out / "database.db", s.image_dir, out / "sparse", mapper=mapper,
                                    seed=args.seed, num_threads=threads, progress=not args.quiet)
    for m in models:
        for e in m.joins:
            done = f"joined into {_folder(m, out)}" if e["joined"] else f"kept apart from {_folder(m, out)}"
            print(f"{say}model {e['model']} ({count(e['images'], 'image')}) {done}: COLMAP's incremental mapper "
                  f"continuing that model registered {e['registered']} of them ({e['seconds']:.1f} s)", flush=True)
        for e in m.repeats:
            print(f"{say}model {e['model']} ({count(e['images'], 'image')}) left out: each of its images is in "
                  f"{_folder(m, out)}", flush=True)
    return fs, result, extra, s, mapper, models


def _args_again(args, paths: list[str], features: tuple[str, int], mapper: str, **more) -> argparse.Namespace:
    """``args`` for the stages before the triangulation again on the images ``paths`` alone, with the SIFT choice
    ``features`` (preset, max_features) and ``mapper``; ``more``: other options changed."""
    preset, max_features = features
    return argparse.Namespace(**dict(vars(args), inputs=paths, image_list=None, recursive=False, preset=preset,
                                     max_features=max_features, mapper=mapper, **more))


def _scenes_alone(args, asked, out: Path, stage: _Stages, camera, threads: int, export, models, mapped,
                  sources) -> list[dict]:
    """Each scene of a collection as good as that scene alone (issue 59): where the collection's size made an
    ``auto`` choice (the SIFT preset, the mapper: :func:`dqm.vision.sfm.choose_preset`, :func:`choose_mapper`)
    that a model of fewer images would not make, that model's registered images go through the stages before the
    triangulation again, alone, with the choices of their own number, into ``out/scenes/<model>/`` (its own
    clusters.npz, database.db and sparse/0; names as in the collection). Where several models are such and all
    their images together would get the same choices, they are redone together, into ``out/scenes/<model>+<model>
    .../``: a scene the collection's mapper cut apart or mixed with another's images is then whole again (the
    270-photo collection of docs/sfm.md with ``--cluster-matches auto``: the global mapper put 8 of entry-P10's
    photos with sacre_coeur's 10 in one model, sharing no 3-D point, and the other 2 in a model of their own);
    each model they make there is then made again from its own images alone, into ``scene-<j>/`` there, and
    replaces the one made together where it registers as many of them: each scene as it is alone, not matched
    with the other's photos. Where the models made together are not taken, each collection model is redone
    alone instead. The models made alone replace the collection's in ``models``, ``mapped`` and ``sources``
    where they register at least as many of the images (each counted once), and, where they are several, where
    no collection model holds two of them joined by 3-D points (:func:`dqm.vision.sfm.linked_across`: the
    collection's mapper held them as one scene that the incremental mapper alone could not). The collection's
    stay in ``sparse/<model>``. Only for a collection the mapper made several models of (one scene alone is not
    redone). Returns what was done, one entry a run alone, for sfm.json."""
    from ..vision.sfm import choose_features, choose_mapper, linked_across, model_numbers, registered_names

    if len(models) < 2:
        return []
    by_name = {name: k for k, name in enumerate(export.names)}
    paths = [str(Path(export.image_dir) / name) for name in export.names]

    def choices(n: int):
        return choose_features(asked.preset, asked.max_features, n), choose_mapper(asked.mapper, n)

    collection = ((args.preset, args.max_features), choose_mapper(args.mapper, export.n_images))
    todo = [k for k, m in enumerate(models) if choices(int(m.rec.num_reg_images())) != collection]
    together = set().union(*(registered_names(models[k].rec) for k in todo)) if todo else set()
    same = {choices(int(models[k].rec.num_reg_images())) for k in todo} == {choices(len(together))}
    batches = [todo] if len(todo) > 1 and same else [[k] for k in todo]

    def redo(names: list[str], folder: Path, before: list, what: str, made=None) -> tuple[dict, list]:
        """``names`` through the stages again alone into ``folder``, against the models ``before`` ((model,
        its numbers) each) that held them; what was done, and the models made alone that replace them ((model,
        numbers, source) each; none where they are kept). ``made``: (features, export summary, SIFT choice) of
        a run alone that held these images: with the same SIFT choice their features are taken from it rather
        than extracted again (each image's features are its own)."""
        n = len(names)
        (preset, max_features), _ = choices(n)
        sub = _args_again(args, [paths[by_name[name]] for name in names], (preset, max_features), asked.mapper)
        features = None
        if made is not None and made[2] == (preset, max_features):
            held = {name: k for k, name in enumerate(made[1].names)}
            features = _features_of(made[0], [held[name] for name in names])
        say = f"{what} ({count(n, 'image')}) again alone, SIFT preset {preset}: "
        print(f"{say}{'QuickMatch' if features is not None else 'extraction, QuickMatch'} and mapping of its images "
              f"into {folder} ...", flush=True)
        entry = {"collection_folder": _folder(before[0][0], out),
                 "collection_folders": [_folder(m, out) for m, _ in before],
                 "images": n, "preset": preset, "max_features": max_features, "extracted": features is None}
        try:
            fs, _, _, s, mapper, own = _match_and_map(sub, folder, stage, camera, threads,
                                                      image_dir=export.image_dir, say=say, features=features)
        except InputError as e:  # the models before stand; what was written stays
            print(f"{say}not redone ({e}); {what} is kept", flush=True)
            entry.update(taken=False, error=str(e))
            return entry, []
        taken, groups, seen = [], [], set()  # the models alone that hold images no larger one does; their images
        for m in own:
            held = registered_names(m.rec)
            if held - seen:
                taken.append(m)
                groups.append(held)
                seen |= held
        joined = next((_folder(m, out) for m, _ in before if linked_across(m.rec, groups)), None) \
            if len(groups) > 1 else None
        got = int(own[0].rec.num_reg_images()) if own else 0
        ok = len(seen) >= n and joined is None
        entry.update(mapper=mapper, registered_alone=got, registered_in_its_models=len(seen), models_alone=len(own),
                     taken=ok, collection_model=before[0][1], collection_models=[numbers for _, numbers in before])
        if ok:
            entry["folder"] = _folder(taken[0], out)
            entry["folders"] = [_folder(m, out) for m in taken]
        kept = f"it replaces {what} ({count(len(taken), 'model')} for {count(len(before), 'model')})" if ok else \
            f"{what} is kept" + (f" ({joined} holds images of two of them joined by 3-D points)" if joined else "")
        print(f"{say}{len(seen)} of {n} images registered in {count(len(own), 'model')}, {got} in its largest; "
              f"{kept}", flush=True)
        return entry, [(m, model_numbers(m.rec), (folder / "database.db", s, fs)) for m in taken] if ok else []

    done, replaced = [], {}
    while batches:
        batch = batches.pop(0)
        names = sorted(set().union(*(registered_names(models[k].rec) for k in batch)), key=by_name.get)
        folder = out / "scenes" / "+".join(models[k].folder.name for k in batch)
        what = " and ".join(_folder(models[k], out) for k in batch)
        entry, taken = redo(names, folder, [(models[k], mapped[k]) for k in batch], f"the collection's {what}")
        done.append(entry)
        if not taken and len(batch) > 1:  # together they are kept: each model alone instead
            batches += [[k] for k in batch]
        if len(taken) > 1:  # the scenes the images make alone, each alone again: as good as that scene alone
            pieces = []
            for j, (m, numbers, source) in enumerate(taken):
                its = sorted(registered_names(m.rec), key=by_name.get)
                part, alone = redo(its, folder / f"scene-{j}", [(m, numbers)], _folder(m, out),
                                   made=(source[2], source[1], choices(len(names))[0]))
                entry.setdefault("scenes", []).append(part)
                pieces += alone or [(m, numbers, source)]
            taken = pieces
            entry["folders"] = [_folder(m, out) for m, _, _ in taken]
        if taken:
            replaced[batch[0]] = taken
            replaced.update({k: [] for k in batch[1:]})
    if replaced:
        rows = [[(models[k], mapped[k], sources[k])] if k not in replaced else replaced[k] for k in range(len(models))]
        firsts = [row[0] for row in rows if row]
        rest = [more for row in rows for more in row[1:]]
        models[:], mapped[:], sources[:] = (list(t) for t in zip(*(firsts + rest)))
    return done


def _features_of(fs: io.FeatureSet, ids: list[int]) -> io.FeatureSet:
    """The features of the images ``ids`` of ``fs``, those images numbered 0.. in the order given."""
    import numpy as np

    renumber = np.full(len(fs.image_names), -1, np.int64)
    renumber[ids] = np.arange(len(ids))
    rows = np.flatnonzero(renumber[fs.image_ids] >= 0)
    rows = rows[np.argsort(renumber[fs.image_ids[rows]], kind="stable")]  # image by image, in the order given
    pick = {name: (None if getattr(fs, name) is None else getattr(fs, name)[rows])
            for name in ("keypoints", "point_ids", "feature_ids")}
    return io.FeatureSet(descriptors=fs.descriptors[rows], image_ids=renumber[fs.image_ids[rows]],
                         image_names=np.asarray(fs.image_names)[ids], **pick)


def _map_again_per_folder(args, asked, out: Path, stage: _Stages, threads: int, export, names: list[str],
                          folder: Path, say: str, first):
    """The images ``names`` (relative to the export's image folder) through the stages before the triangulation
    again into ``folder``, with one camera per folder; mapped by COLMAP's incremental mapper unless a mapper was
    asked for (it checks every camera against COLMAP's bounds as it registers images, the global mapper does not:
    cmu_hotel with ``--cluster-matches auto``, the global mapper's model with one camera had 401 points, the
    incremental mapper's 2,856; docs/sfm.md). ``first``: the run's features (every image, in the export's
    order), QuickMatch's result and extras; where the images get the run's SIFT choice (or the run started from
    --clusters), their features are taken from it rather than extracted again (each image's features are its
    own), and where they are every image, its clusters too (only the cameras differ). Returns
    :func:`_match_and_map`'s result."""
    from ..vision import colmap
    from ..vision.sfm import choose_features

    paths = [str(Path(export.image_dir) / name) for name in names]
    mapper = "incremental" if asked.mapper == "auto" else asked.mapper
    run_choice = (args.preset, args.max_features)
    choice = run_choice if asked.preset is None else choose_features(asked.preset, asked.max_features, len(names))
    sub = _args_again(args, paths, choice, mapper, single_camera=False, single_camera_per_folder=True)
    camera = colmap.camera_options(args.camera_model or colmap.DEFAULT_CAMERA_MODEL, "per-folder", None)
    features = clusters = None
    if choice == run_choice:
        fs, result, extra = first
        if fs.descriptors.shape[1] == 0 and list(names) != list(export.names):
            raise InputError("the features have no descriptors (a distributed job's CLUSTERS file without "
                             "--features), so these images cannot be matched again")
        if list(names) == list(export.names):
            features, clusters = fs, (result, extra)
        else:
            by_name = {name: k for k, name in enumerate(export.names)}
            features = _features_of(fs, [by_name[name] for name in names])
    return _match_and_map(sub, folder, stage, camera, threads, image_dir=export.image_dir, say=say,
                          features=features, clusters=clusters)


def _shared_camera_unfit(args, export, names: list[str]) -> str | None:
    """Why the images ``names`` are not mapped again with one camera per folder, or None
    (:func:`dqm.vision.colmap.shared_camera_unfit`: one size a folder, no EXIF focal length)."""
    from ..vision import colmap

    if camera_sharing(args) != "per-image":
        return "the images share cameras already"
    return colmap.shared_camera_unfit([str(Path(export.image_dir) / name) for name in names], export.image_dir)


def _few_registered_again(args, asked, out: Path, stage: _Stages, threads: int, export, models, mapped,
                          sources, first) -> dict | None:
    """Where the mapper's models hold fewer than half of the images, each with a camera of its own, and one camera
    per folder fits them (one size a folder, no EXIF focal length: a video's frames), every image mapped again with
    one camera per folder into ``out/shared-camera/all/``: COLMAP's incremental mapper, which drops an image whose
    camera it calls bogus, registered 12 of cmu_hotel's 101 frames with a camera a frame (``--mapper
    incremental``; the same mapper with one camera, 101). The new models replace all of ``models``, ``mapped`` and
    ``sources`` where their largest registers more images than the first's, with no more bogus cameras; otherwise
    the first stay, with a warning. Returns what was done, for sfm.json (None: nothing to do)."""
    from ..vision.sfm import bogus_cameras, model_numbers

    registered = registered_images(models)[0]
    if 2 * registered >= export.n_images or _shared_camera_unfit(args, export, list(export.names)) is not None:
        return None
    n, bad = (int(models[0].rec.num_reg_images()), bogus_cameras(models[0].rec)) if models else (0, [])
    folder = out / "shared-camera" / "all"
    entry = {"model_folder": _folder(models[0], out) if models else None, "images": n, "bogus_cameras": len(bad),
             "after": "map", "registered_of": export.n_images, "taken": False}
    say = "every image again, one camera per folder: "
    print(f"{registered} of {export.n_images} images registered with a camera each; they share one size a folder "
          f"and have no EXIF focal length, so they are mapped again with one camera per folder into {folder} ...",
          flush=True)
    try:
        fs, _, _, s, mapper, own = _map_again_per_folder(args, asked, out, stage, threads, export,
                                                         list(export.names), folder, say, first)
    except InputError as e:  # the first models stand; what was written stays
        entry["error"] = str(e)
        LOG.warning("the images not mapped again (%s); the first mapping stands", e)
        return entry
    numbers = model_numbers(own[0].rec if own else None)
    got, still = numbers["registered"], numbers["bogus_cameras"]
    entry.update(mapper=mapper, registered_again=got, bogus_cameras_again=still, points_again=numbers["points"],
                 taken=got > n and still <= len(bad), model_before=mapped[0] if mapped else model_numbers(None))
    if entry["taken"]:
        models[:], mapped[:] = own, [model_numbers(m.rec) for m in own]
        sources[:] = [(folder / "database.db", s, fs)] * len(own)
        entry["folder"] = _folder(own[0], out)
        print(f"{say}{got} of {export.n_images} images registered, {still} bogus cameras, "
              f"{own[0].rec.num_points3D():,} 3-D points: its models replace the first", flush=True)
    else:
        LOG.warning("every image again with one camera per folder: %d of %d registered in its largest model (%d "
                    "before); the first mapping stands", got, export.n_images, n)
    return entry


def _shared_camera_again(args, asked, out: Path, stage: _Stages, threads: int, export, models, mapped,
                         sources, first, only=None, after: str = "map") -> dict[int, dict]:
    """A model with cameras COLMAP calls bogus (:func:`dqm.vision.sfm.bogus_cameras`; its incremental mapper
    drops such an image) mapped again with one camera per folder (:func:`_map_again_per_folder`), where each image
    had a camera of its own and one per folder fits (:func:`dqm.vision.colmap.shared_camera_unfit`: one size a
    folder, no EXIF focal length): a video's frames, where a camera a frame leaves focal length and distortion free
    for every frame (cmu_hotel alone: 101 bogus of 101; in the 270-photo collection: 30 of 101). Its images (every
    image of the run where the mapper made one model) go through the stages before the triangulation again into
    ``out/shared-camera/<k>/``, ``k`` the model's place in ``models``. Its model replaces the first in
    ``models``, ``mapped`` and ``sources`` where it registers at least as many images with fewer bogus cameras
    and at least as many 3-D points (one camera for all of a true single camera's images is not better
    everywhere: docs/sfm.md); otherwise the first stays, with a warning. ``only``: the places in ``models`` to look
    at (None: every model); ``after``: the stage whose cameras are looked at, ``map`` or ``triangulate`` (the last
    stage's bundle adjustment can leave cameras bogus that the mapper's were not: cmu_hotel in the 270-photo
    collection with ``--cluster-matches auto``, 0 bogus before it and 33 after; the points compared are the
    mappers' in both cases). Returns what was done, one entry a model by its place in ``models``, for
    sfm.json."""
    from ..vision.sfm import bogus_cameras, model_numbers, registered_names

    by_name = {name: k for k, name in enumerate(export.names)}
    done = {}
    for k, m in enumerate(list(models)):
        if only is not None and k not in only:
            continue
        bad, n = bogus_cameras(m.rec), int(m.rec.num_reg_images())
        if not bad:
            continue
        names = list(export.names) if len(models) == 1 else sorted(registered_names(m.rec), key=by_name.get)
        entry = {"model_folder": _folder(m, out), "images": n, "bogus_cameras": len(bad), "after": after,
                 "taken": False}
        done[k] = entry
        when = " after the last stage's bundle adjustment" if after == "triangulate" else ""
        bogus = f"{_folder(m, out)}: {len(bad)} of {n} registered images have a camera COLMAP calls bogus{when} " \
                f"(focal length or distortion out of bounds, e.g. {bad[0]})"
        unfit = _shared_camera_unfit(args, export, names)
        if unfit is not None:
            entry["unfit"] = unfit
            LOG.warning("%s; not mapped again with one camera per folder (%s): the model's cameras are not to be "
                        "trusted", bogus, unfit)
            continue
        folder = out / "shared-camera" / str(k)
        say = f"{_folder(m, out)} again, one camera per folder: "
        print(f"{bogus}; its {count(len(names), 'image')} share one size a folder and have no EXIF focal length, "
              f"so they are mapped again with one camera per folder into {folder} ...", flush=True)
        try:
            fs, _, _, s, mapper, own = _map_again_per_folder(args, asked, out, stage, threads, export, names, folder,
                                                             say, first)
        except InputError as e:  # the first model stands; what was written stays
            entry["error"] = str(e)
            LOG.warning("%s not mapped again (%s); %s is kept and its cameras are not to be trusted",
                        _folder(m, out), e, entry["model_folder"])
            continue
        numbers = model_numbers(own[0].rec if own else None)
        got, still = numbers["registered"], numbers["bogus_cameras"]
        entry.update(mapper=mapper, registered_again=got, bogus_cameras_again=still, points_again=numbers["points"],
                     taken=got >= n and still < len(bad) and numbers["points"] >= mapped[k]["points"],
                     model_before=mapped[k])
        if entry["taken"]:
            models[k], mapped[k], sources[k] = own[0], numbers, (folder / "database.db", s, fs)
            entry["folder"] = _folder(own[0], out)
            print(f"{say}{got} of {n} images registered, {still} bogus cameras, "
                  f"{own[0].rec.num_points3D():,} 3-D points: it replaces {entry['model_folder']}", flush=True)
        else:
            LOG.warning("%s again with one camera per folder: %d of %d images registered, %d bogus cameras, %d 3-D "
                        "points (%d before); %s is kept", _folder(m, out), got, n, still, numbers["points"],
                        mapped[k]["points"], entry["model_folder"])
    return done


def registered_images(models) -> tuple[int, int]:
    """The images registered in any of ``models``, and how many of them more than one model holds too (COLMAP's
    incremental mapper can start a model from images another model has registered: sacre_coeur's 10 photos gave
    a model of all 10 and one of 2 of them)."""
    from collections import Counter

    from ..vision.sfm import registered_names

    held = Counter(name for m in models for name in registered_names(m.rec))
    return len(held), sum(1 for n in held.values() if n > 1)


def _models_report(models, mapped, truth, model_dir: Path) -> list[dict]:
    """Every model's numbers (before and after triangulation) and, with ground truth, its cameras against the
    truth of its own images (in a collection of several scenes, each model is one scene)."""
    from ..vision import poses
    from ..vision.sfm import model_numbers

    out = []
    for m, before in zip(models, mapped):
        entry = dict(model_numbers(m.rec), folder=_folder(m, model_dir), before_triangulation=before, joins=m.joins,
                     repeats=m.repeats)
        if truth is not None:
            names = {Path(image.name).name for image in m.rec.images.values()}
            own = {k: v for k, v in truth.items() if Path(k).name in names}
            if own:
                entry["poses"] = poses.evaluate_poses(poses.poses_of(m.rec), own).as_dict()
        out.append(entry)
    return out


def _clusters_across_models(models, export, fs, labels) -> dict:
    """The clusters whose members lie in images of two models or more (QuickMatch joined them before COLMAP's
    verification and mapper kept the models apart; on a collection of several scenes, clusters across scenes),
    and their features in registered images."""
    import numpy as np

    from ..vision.sfm import clusters_across, registered_names

    by_name = {name: k for k, name in enumerate(export.names)}
    model_of = np.full(len(export.names), -1)
    for k, m in enumerate(models):
        for name in registered_names(m.rec):
            model_of[by_name[name]] = k
    where = model_of[fs.image_ids]
    across = clusters_across(labels, where)
    return {"clusters": int(len(across)), "features": int(np.isin(np.asarray(labels)[where >= 0], across).sum())}


def run(args) -> int:
    from ..vision import colmap, poses
    from ..vision.sfm import (
        GLOBAL_FROM,
        SMALL_SCENE_PRESET,
        choose_features,
    )

    t0 = time.perf_counter()
    colmap.require_pycolmap(what="dqm sfm (COLMAP's mapper)")
    mode = camera_sharing(args)
    camera = colmap.camera_options(args.camera_model or colmap.DEFAULT_CAMERA_MODEL, mode, None)
    if args.seed < 0 or args.mapper_threads < 0 or args.partners < 0:
        raise InputError(f"--seed, --mapper-threads and --partners must be >= 0, got {args.seed}, "
                         f"{args.mapper_threads} and {args.partners}")
    if args.max_features is not None and args.max_features < 0:
        raise InputError(f"--max-features must be >= 0 (0 = no limit), got {args.max_features}")
    threads = args.mapper_threads or -1
    made = None
    if args.features is not None and args.clusters is None:
        raise InputError("--features gives the descriptors of --clusters FILE (a distributed job's); without "
                         "--clusters, give images")
    if args.image_dir is not None and args.clusters is None:
        raise InputError("--image-dir says where the images of --clusters FILE are now; without --clusters, give the "
                         "images themselves")
    if args.clusters is not None:
        made = _from_clusters(args)
    elif not args.inputs and not args.image_list:
        raise InputError("no images: give image folders, globs or files, or --image-list")
    truth = None
    # as asked, before auto chooses for the collection
    asked = argparse.Namespace(preset=args.preset, max_features=args.max_features, mapper=args.mapper)
    if made:  # the file's: what its run asked for, else the choice it holds (None: unknown, as a distributed job's)
        asked.preset, asked.max_features = args.asked_preset, args.asked_max_features
    args.asked_preset, args.asked_max_features = asked.preset, asked.max_features
    n_images = 0
    if args.gt or args.preset == "auto" or mode != "per-image" or made:  # the images named before any work
        from ..vision.features import collect_images

        paths = [Path(name) for name in made[0].image_names] if made else \
            collect_images(args.inputs, recursive=args.recursive, image_list=args.image_list)
        names = [p.name for p in paths]
        n_images = len(names)
        if args.gt:  # read and matched to the images' names
            truth = poses.restrict(poses.read_ground_truth(args.gt), names, f"--gt {args.gt}")
        colmap.check_camera_sharing(paths, camera)  # a shared camera needs one image size
    if made:
        grown = " grown by geometry (dqm match's default on images; dqm sfm's is not to grow them: docs/sfm.md)" \
            if args.guided else ""
        print(f"features and clusters of {args.clusters}{grown}: {count(len(made[0]), 'feature')} of "
              f"{count(n_images, 'image')}", flush=True)
    else:
        args.preset, args.max_features = choose_features(args.preset, args.max_features, n_images)
    if asked.preset == "auto" and not made:
        cap = f", at most {args.max_features:,} features an image" if args.max_features else ""
        print(f"SIFT preset {args.preset}{cap} (auto: {count(n_images, 'image')}, {SMALL_SCENE_PRESET} below "
              f"{GLOBAL_FROM})", flush=True)
    out = _out_dir(args.out)
    try:
        return _stages(args, out, made, asked, camera, threads, truth, t0)
    except BaseException:  # Ctrl-C, a failed mapper, ...: the clusters made are not lost
        if (out / "clusters.npz").exists():
            print(f"note: {_goes_on(out)}", file=sys.stderr)
        raise


def _goes_on(out: Path) -> str:
    return f"{out / 'clusters.npz'} holds the features and the clusters: dqm sfm --clusters {out / 'clusters.npz'} " \
           "--out NEW_DIR goes on from them"


def _stages(args, out: Path, made, asked, camera, threads: int, truth, t0: float) -> int:
    """:func:`run`'s stages, its inputs checked: ``made``, what --clusters gave (None: extract and match)."""
    from ..vision import poses
    from ..vision.sfm import model_figure, model_numbers

    stage = _Stages()
    if made:  # MODEL_DIR holds its clusters as a run from images does
        fs, result, extra = made
        with stage("export"):
            with outputs.atomic_output(out / "clusters.npz") as tmp:
                shutil.copyfile(args.clusters, tmp)
            io.save_tracks_csv(out / "tracks.csv", result.labels, fs.image_ids, fs.keypoints, fs.image_names)
    fs, result, extra, s, mapper, models = _match_and_map(args, out, stage, camera, threads,
                                                          features=made and made[0], clusters=made and made[1:])
    first = (fs, result, extra)
    mapped = [model_numbers(m.rec) for m in models]
    sources = [(out / "database.db", s, fs)] * len(models)  # each model's database, export and features
    if made and asked.preset is None and len(models) > 1:
        print(f"note: the {len(models)} models are not made again alone with the choices of their size "
              f"({args.clusters} does not say how its features were made; give the images for that)", flush=True)
    alone = [] if made and asked.preset is None else \
        _scenes_alone(args, asked, out, stage, camera, threads, s, models, mapped, sources)
    few = _few_registered_again(args, asked, out, stage, threads, s, models, mapped, sources, first)
    shared = few is not None and few["taken"]  # the models have a camera per folder now
    again = {} if shared else _shared_camera_again(args, asked, out, stage, threads, s, models, mapped, sources,
                                                   first)

    def last_stage(places) -> None:
        with stage("triangulate"):
            for k in places:  # every model (each scene of a mixed collection): their images are disjoint
                m, (database, export, features) = models[k], sources[k]
                m.rec, ts = _triangulate(m.rec, database, export, features, m.folder, args.seed, threads,
                                         args.threads, args.bundle_adjust, not args.quiet)
                print(ts.summary() if len(models) == 1 else f"{_folder(m, out)}: {ts.summary()}")

    if models and args.triangulate:
        last_stage(range(len(models)))
        # cameras the last stage's bundle adjustment left bogus where the mapper's were not: mapped again as the
        # mapper's would have been, and the new model through the last stage
        later = {} if shared else _shared_camera_again(args, asked, out, stage, threads, s, models, mapped, sources,
                                                       first, only=set(range(len(models))) - set(again),
                                                       after="triangulate")
        last_stage(sorted(k for k, e in later.items() if e["taken"]))
        again.update(later)
    report = {"images": s.n_images, "features": len(fs), "options": {
        "preset": args.preset, "max_features": args.max_features, "guided": bool(args.guided),
        "verify": bool(args.verify), "mapper": mapper, "seed": args.seed, "partners": args.partners,
        "cluster_matches": args.cluster_matches, "clusters": args.clusters,
        "mapper_threads": args.mapper_threads, "triangulate": bool(args.triangulate),
        "bundle_adjust": bool(args.triangulate and args.bundle_adjust)},
        "model": model_numbers(models[0].rec if models else None),
        "model_before_triangulation": mapped[0] if models else model_numbers(None),
        "pairs": {"written": s.n_image_pairs, "left_out": s.n_pairs_left_out,
                  "beyond_partners": s.n_pairs_beyond, "verified": s.n_verified_pairs,
                  "dropped_as_weak": s.n_pairs_dropped, "matches": s.n_matches,
                  "log_spaced_clusters": s.n_spaced_clusters},
        "models": _models_report(models, mapped, truth, out), "scenes_alone": alone,
        "shared_camera_again": [again[k] for k in sorted(again)], "few_registered_again": few,
        "clusters_across_models": _clusters_across_models(models, s, fs, result.labels)}
    report["times"] = dict(stage.times, total=time.perf_counter() - t0)
    report["peak_memory_bytes"] = stage.peaks
    if not models:
        outputs.write_json(out / "sfm.json", report)
        print(f"no model: pycolmap's mapper registered no image pair ({stage.times['map']:.1f} s); the clusters and "
              f"the database are in {out} ({_goes_on(out)}, --mapper to choose another mapper)")
        return 1
    m = report["model"]
    print(f"model: {m['registered']} of {s.n_images} images registered, {m['points']:,} 3-D points, mean track "
          f"length {m['track']:.2f}, mean reprojection error {m['reproj']:.3f} px; {stage.line()}, "
          f"{report['times']['total']:.1f} s in all")
    if len(models) > 1:
        across = report["clusters_across_models"]
        registered, twice = registered_images(models)
        more = f" ({count(twice, 'image')} in more than one)" if twice else ""
        print(f"{len(models)} models, {registered} of {s.n_images} images registered{more}: "
              + "; ".join(f"{e['folder']} {e['registered']} images, {e['points']:,} points" for e in report["models"])
              + f"; {count(across['clusters'], 'cluster')} of QuickMatch's joined images of two models")
    if truth is not None:
        scores = poses.evaluate_poses(poses.poses_of(models[0].rec), truth)
        report["poses"] = scores.as_dict()
        print(scores.line())
    for entry in report["models"]:
        if entry["bogus_cameras"]:
            LOG.warning("%s: %d of %d registered images have a camera COLMAP calls bogus (focal length or "
                        "distortion out of its bounds): their poses are not to be trusted", entry["folder"],
                        entry["bogus_cameras"], entry["registered"])
    outputs.write_json(out / "sfm.json", report)
    figures = []  # after sfm.json: what is computed is written before anything else can fail
    for k, (m, entry) in enumerate(zip(models, report["models"])):
        figures.append(out / ("model.png" if k == 0 else f"model-{k + 1}.png"))
        model_figure(m.rec, figures[-1], f"{_folder(m, out)}: {entry['registered']} of {s.n_images} images, "
                                         f"{entry['points']:,} points")
    redone = "".join(f"{out}/{where}, " for where, done in (("scenes", alone), ("shared-camera", again or few)) if done)
    print(f"wrote {out}/sparse, {redone}{', '.join(str(f) for f in figures)}, {out / 'sfm.json'}")
    return 0

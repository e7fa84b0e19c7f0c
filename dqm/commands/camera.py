"""A camera node: feed the images of a folder, a glob or files to ``dqm stream`` at a given rate.

    dqm camera frames/ --connect tcp/127.0.0.1:7447 --job cams --camera 0 --rate 2
    dqm camera 'cam1/*.jpg' --connect tcp/ROUTER:7447 --job cams --camera 1 --rate 5 --loop --limit 100

IMAGES: folders, glob patterns or image files, and/or --image-list FILE (the same
inputs, in the same order, as dqm extract; --recursive too). Under access control
(--tls-cert or --user) the node first checks that the router lets it put as camera C
(the roster line 'camera NAME C'), else exits 2 naming the line. It waits for the
stream's liveliness token (dqm/<job>/alive/stream, up to --wait seconds), then
extracts SIFT (the --preset / --max-features options of dqm extract, but the default
preset is rootsift, the online matcher's, where dqm extract's is sfm) and puts one
`image` message per image on dqm/<job>/stream/images/from/C, one every 1/--rate seconds
(an image whose SIFT takes longer is put as soon as it is ready). Every message
carries the image's name (--names: its absolute path, its file name, or none) and
keypoints, so that the stream's --out file can be drawn with dqm plot pair / clusters.

Image ids: camera C numbers its images k = 0, 1, 2, ... (--first-index to start
elsewhere, e.g. when a node restarts against a running stream) and sends image id
C * 1000000000 + k, so several camera nodes with distinct --camera ids never
collide on one stream (camera 2's image 17 is 2000000017). With --loop the images
are sent again and again (features computed once), each time under new ids; --limit
stops after N images. An image without SIFT features is skipped (the stream would
refuse it).

A progress bar on a terminal (--quiet: none), a line per image with --verbose, a
summary line at the end. Exit codes: 0 done, 1 the stream went away (its token gone
for --wait seconds), 2 bad input, no router or no stream, 130 interrupted (Ctrl-C),
143 terminated (SIGTERM); Ctrl-C / SIGTERM finish the current image first.
"""
from __future__ import annotations

import itertools
import logging
import sys
from pathlib import Path
from typing import Dict, Iterator, List, Set

from .extract import add_image_options
from .runtime_options import add_tls, tls_from

NAME = "camera"
HELP = "feed images from a folder to dqm stream at a given rate (a camera node)"

#: what an image message names its image by
NAME_MODES = ("path", "file", "none")


def add_arguments(p) -> None:
    p.add_argument("inputs", nargs="*", metavar="IMAGES",
                   help="image folders, glob patterns or files (or none, with --image-list)")
    p.add_argument("--connect", required=True, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--job", default="stream", help="the stream's job id (default: stream, as dqm stream's)")
    p.add_argument("--camera", default="0", metavar="C",
                   help="this node's camera id, 0..2147483647 (default 0); give every node of a stream its own")
    p.add_argument("--rate", default="1", metavar="HZ", help="images per second (default 1)")
    p.add_argument("--loop", action="store_true", help="send the images again and again (new ids each pass)")
    p.add_argument("--limit", default=None, metavar="N", help="stop after N images")
    p.add_argument("--first-index", default="0", metavar="K",
                   help="number of the first image (image id = camera * 10^9 + number; default 0)")
    p.add_argument("--names", choices=NAME_MODES, default="path",
                   help="name sent with each image: its absolute path (default), its file name (dqm plot "
                        "--image-dir finds it), or none")
    p.add_argument("--wait", default="30", metavar="SECONDS",
                   help="how long to wait for the stream (at the start, and if it goes away; default 30)")
    p.add_argument("--connect-timeout", default="5", metavar="SECONDS", help="seconds of retries to reach the router")
    add_image_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--verbose", action="store_true", help="a line per image (on standard output)")
    add_tls(p)


def _number(text, option: str, integer: bool = False, low: float = 0.0, high: float = float("inf"),
            low_ok: bool = True):
    """``text`` as a number within [low, high] (``(low, high]`` unless ``low_ok``), or InputError naming ``option``."""
    from ..validation import InputError

    try:
        v = int(text) if integer else float(text)
    except (TypeError, ValueError):
        raise InputError(f"{option} must be {'a whole number' if integer else 'a number'}, got {text!r}") from None
    if not (low <= v if low_ok else low < v) or not v <= high or v == float("inf"):
        def fmt(x: float) -> str:
            return str(int(x)) if integer else f"{x:g}"

        bound = f"{'at least' if low_ok else 'above'} {fmt(low)}" + (f" and at most {fmt(high)}" if high < 1e300
                                                                     else "")
        raise InputError(f"{option} must be {bound}, got {text}")
    return v


def frames(paths: List[Path], args, skipped: List[str], empty: List[str]) -> Iterator["object"]:
    """The images as :class:`dqm.runtime.stream.Frame` s, SIFT extracted as they are taken (once, with
    --loop); unreadable images (with --skip-bad-images) and images without features are left out and
    listed in ``skipped`` / ``empty``."""
    from ..runtime.stream import Frame
    from ..validation import InputError
    from ..vision.features import extract

    cache: Dict[Path, Frame] = {}
    gone: Set[Path] = set()
    while True:
        any_sent = False
        for p in paths:
            if p in gone:
                continue
            f = cache.get(p)
            if f is None:
                try:
                    feats = extract(p, args.preset, args.max_features)
                except InputError:
                    if not args.skip_bad_images:
                        raise
                    skipped.append(str(p))
                    gone.add(p)
                    continue
                if len(feats) == 0:
                    empty.append(str(p))
                    gone.add(p)
                    continue
                name = {"path": str(p.resolve()), "file": p.name, "none": ""}[args.names]
                f = Frame(name, feats.descriptors, feats.keypoints)
                if args.loop:
                    cache[p] = f
            any_sent = True
            yield f
        if not args.loop or not any_sent:
            return


def run(args) -> int:
    from ..distributed import keys
    from ..progress import ProgressBar
    from ..runtime import stream
    from ..runtime.bus import AccessDenied, RouterUnreachable, check_endpoint
    from ..validation import InputError
    from ..vision.features import check_preset, collect_images, unreadable_images

    check_endpoint(args.connect)
    keys.check_job(args.job)
    rate = _number(args.rate, "--rate", low=0.0, low_ok=False)
    camera = _number(args.camera, "--camera", integer=True, high=stream.MAX_CAMERA)
    first = _number(args.first_index, "--first-index", integer=True, high=stream.IMAGES_PER_CAMERA - 1)
    limit = None if args.limit is None else _number(args.limit, "--limit", integer=True, low=1)
    wait_s = _number(args.wait, "--wait", low=0.0, low_ok=False)
    connect_s = _number(args.connect_timeout, "--connect-timeout", low=0.0, low_ok=False)
    check_preset(args.preset, args.max_features)  # refuses a bad --max-features before any work
    tls = tls_from(args, listen=False)
    paths = collect_images(args.inputs, recursive=args.recursive, image_list=args.image_list)
    bad = unreadable_images(paths)
    if bad and not args.skip_bad_images:
        raise InputError(f"cannot read image(s) (not an image or empty): {len(bad)} file(s): "
                         + ", ".join(str(p) for p in bad[:5]) + (" ..." if len(bad) > 5 else "")
                         + "; --skip-bad-images leaves them out")
    paths = [p for p in paths if p not in bad]
    if not paths:
        raise InputError("no readable image among the inputs")
    planned = limit if limit is not None else (0 if args.loop else len(paths))
    if first + planned > stream.IMAGES_PER_CAMERA:
        raise InputError(f"--first-index {first} leaves fewer than {planned} image numbers below "
                         f"{stream.IMAGES_PER_CAMERA} (image id = camera * {stream.IMAGES_PER_CAMERA} + number)")
    skipped, empty = [str(p) for p in bad], []
    source = frames(paths, args, skipped, empty)
    if limit is not None:
        source = itertools.islice(source, limit)
    bar = ProgressBar(f"camera {camera}", force=False if (args.quiet or args.verbose) else None, unit="images")
    notes, level = None, stream.LOG.level  # the node's notes (waiting for the stream, ...) where its progress
    if args.verbose or (bar.enabled and not args.quiet):  # shows, or with --verbose
        notes = logging.StreamHandler(sys.stderr)
        notes.setFormatter(logging.Formatter(f"[camera {camera}] %(message)s"))
        stream.LOG.addHandler(notes)
        stream.LOG.setLevel(logging.INFO)
    total = len(paths) if limit is None else (limit if args.loop else min(limit, len(paths)))

    def progress(n: int) -> None:  # with --loop and no --limit: one bar per pass over the images
        bar(n if limit is not None or not args.loop else (n - 1) % total + 1, total)

    try:
        code = stream.main_camera(args.connect, args.job, camera, source, rate=rate, first_index=first, tls=tls,
                                  connect_timeout_s=connect_s, wait_s=wait_s, progress=progress,
                                  lines=args.verbose)
    except (RouterUnreachable, AccessDenied, stream.StreamUnavailable) as exc:
        raise InputError(str(exc)) from None
    finally:
        bar.close()
        if notes is not None:
            stream.LOG.removeHandler(notes)
            stream.LOG.setLevel(level)
    if skipped:
        print(f"warning: skipped {len(skipped)} unreadable image(s): {', '.join(skipped[:5])}"
              + (" ..." if len(skipped) > 5 else ""))
    if empty:
        print(f"note: no SIFT features in {len(empty)} image(s), not sent: {', '.join(empty[:5])}"
              + (" ..." if len(empty) > 5 else ""))
    return code

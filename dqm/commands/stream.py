"""Online QuickMatch over zenoh: camera nodes put images, the stream publishes what changed.

    dqm stream --connect tcp/127.0.0.1:7447 --job cams
    dqm stream --connect tcp/ROUTER:7447 --job cams --window 50 --idle 30 --out clusters.npz

Camera nodes (dqm camera, one per camera) put one `image` message per image (msgpack,
dqm.distributed.messages: image_id, name, time, descriptors, keypoints) on
dqm/<job>/stream/images/from/<camera>, once the stream's liveliness token dqm/<job>/alive/stream
is present. After every add (and every removal by --window) the stream publishes a
`changes` message (the cluster events, the image and its name, the counts) on
dqm/<job>/stream/changes. Its clusters equal dqm match --kernel quadratic on the
images present, in arrival order.

Malformed messages (bad msgpack, version, kind, job, arrays, dimensions, an image
received before, an image without features) are dropped and counted by reason; the
stream goes on. It stops on Ctrl-C / SIGTERM, after --images accepted images or
--idle seconds without a message, then writes --out (a CLUSTERS file of the images
present, numbered 0..K-1 in arrival order -- params stream_image_ids holds the
stream's ids -- with image_names and keypoints when every image sent them, so that
dqm plot pair / clusters can draw it) and prints a summary.

Exit codes: 0 done, 2 bad input or no router, 130 interrupted, 143 terminated
(SIGTERM); --out is written in every case once an image was accepted.
"""
import argparse

from .. import outputs
from ..core.params import FINITE_KERNEL
from ..validation import positive_int_arg
from .param_options import add_quickmatch_params
from .runtime_options import add_tls, tls_from

NAME = "stream"
HELP = "online matching of images that camera nodes put over zenoh"


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return v


def add_arguments(p) -> None:
    p.add_argument("--connect", required=True, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--job", default="stream", help="job id: the keys live under dqm/<job>/ (default: stream)")
    add_quickmatch_params(p, ("rho",), kernel_default=FINITE_KERNEL, number_type=_positive_float,
                          notes={"rho": f"; the kernel is the finite {FINITE_KERNEL} one"})
    p.add_argument("--window", type=positive_int_arg, default=None, metavar="N",
                   help="keep at most N images: before adding an image beyond N, remove the oldest (its change "
                        "set is published too)")
    p.add_argument("--images", type=positive_int_arg, default=None, metavar="N", help="stop after N accepted images")
    p.add_argument("--idle", type=_positive_float, default=None, metavar="SECONDS",
                   help="stop after this many seconds without a message")
    p.add_argument("--out", default=None, metavar="CLUSTERS.npz",
                   help="at the end, write the images present and their clusters (format: dqm/io.py)")
    outputs.add_overwrite_option(p)
    p.add_argument("--quiet", action="store_true", help="no line per image (the default when not a terminal)")
    p.add_argument("--verbose", action="store_true", help="a line per image even when not a terminal")
    p.add_argument("--connect-timeout", type=_positive_float, default=5.0,
                   help="seconds of retries to reach the router")
    p.add_argument("--max-message-bytes", type=positive_int_arg, default=64 << 20, help="reject larger messages")
    add_tls(p)


def run(args) -> int:
    import sys

    from ..distributed import keys
    from ..runtime.bus import AccessDenied, JobIdInUse, RouterUnreachable, check_endpoint
    from ..validation import InputError

    check_endpoint(args.connect)
    keys.check_job(args.job)
    if args.out:
        outputs.check_file(args.out, "--out", suffixes=(".npz",), overwrite=args.overwrite)
    tls = tls_from(args, listen=False)
    lines = not args.quiet and (args.verbose or sys.stdout.isatty())
    from ..runtime.stream import main_stream

    try:
        return main_stream(args.connect, args.job, rho=args.rho, window=args.window, max_images=args.images,
                           idle_s=args.idle, out=args.out, lines=lines, tls=tls,
                           connect_timeout_s=args.connect_timeout, max_bytes=args.max_message_bytes)
    except (RouterUnreachable, JobIdInUse, AccessDenied) as exc:
        raise InputError(str(exc)) from None

"""Write a generated multi-view scene with exact ground truth (no download needed).

The folder gets the Oxford layout (img1.png .. imgN.png, H1to2p .. H1toNp), so
every dqm command that reads images or homography sequences reads it:

    dqm scene /tmp/scene --seed 3
    dqm match /tmp/scene --out /tmp/clusters.npz
    dqm plot pair /tmp/clusters.npz --truth /tmp/scene --out /tmp/pair.png
    dqm evaluate /tmp/scene --out-dir /tmp/eval
"""
from __future__ import annotations

import logging

from .. import outputs
from ..validation import InputError
from ..vision.scenes import generate_scene

NAME = "scene"
#: what dqm scene writes in its folder (an Oxford-layout sequence), refused when already there
SCENE_FILES = ("img*", "H1to*")
HELP = "write a generated multi-view scene (images + homographies) to a folder"

LOG = logging.getLogger("dqm.commands")


def add_arguments(p) -> None:
    p.add_argument("out", metavar="FOLDER", help="folder to write (created if needed; a folder that already holds "
                                                 "img* or H1to* files is refused unless --overwrite)")
    outputs.add_overwrite_option(p, help="replace the img* and H1to* files of an existing folder")
    p.add_argument("--images", type=int, default=6, help="number of views (default 6)")
    p.add_argument("--size", type=int, nargs=2, default=(480, 640), metavar=("H", "W"), help="view size")
    p.add_argument("--seed", type=int, default=0, help="generator seed")
    p.add_argument("--viewpoint", type=float, default=1.0, help="perspective change strength (0 = none)")
    p.add_argument("--photometric", type=float, default=1.0, help="gain/bias/gamma change strength")
    p.add_argument("--noise", type=float, default=3.0, help="sensor noise, grey levels")


def run(args) -> int:
    if args.images < 2:
        raise InputError("--images must be at least 2")
    outputs.check_dir(args.out, "FOLDER", SCENE_FILES, overwrite=args.overwrite)
    LOG.info("scene: %d images of %d x %d px (seed %d), written to %s with their homographies", args.images,
             args.size[1], args.size[0], args.seed, args.out)
    scene = generate_scene(args.images, tuple(args.size), seed=args.seed, viewpoint=args.viewpoint,
                           photometric=args.photometric, noise=args.noise)
    seq = scene.write(args.out)
    print(f"wrote {len(seq.image_paths)} images and {len(seq.image_paths) - 1} homographies to {args.out}")
    return 0

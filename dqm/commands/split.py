"""Split a FEATURES file into one FEATURES file per agent of a distributed job.

    dqm split all.npz --agents 4 --out split/                  # image k -> agent k mod 4
    dqm split all.npz --image-lists robot0.txt robot1.txt --out split/

Each agent gets whole images: with --agents M, the k-th image (in order of image
id) goes to agent k mod M, as `dqm run` and the simulator deal them; with
--image-lists, list i names the images of agent i (one image id, image path or
file name per line; blank lines and # comments are skipped). The parts keep the
keypoints, the image names, the ground truth and the feature ids (the file's
own, or its row numbers), so the job's CLUSTERS file (dqm coordinator) has rows
and images the original file can be matched to. Writes OUT/agent<i>.npz and
prints the `dqm agent` command of each (deploy/README.md).
"""
from __future__ import annotations

import logging
import shlex
from pathlib import Path
from typing import List

import numpy as np

from .. import outputs
from ..validation import InputError, positive_int_arg
from ..wording import count

NAME = "split"
#: what dqm split writes in its folder
AGENT_FILES = ("agent*.npz",)
HELP = "split a FEATURES file into one file per agent (whole images each)"

LOG = logging.getLogger("dqm.commands")


def add_arguments(p) -> None:
    p.add_argument("features", metavar="FEATURES.npz", help="the FEATURES file to split (docs/formats.md)")
    how = p.add_mutually_exclusive_group(required=True)
    how.add_argument("--agents", type=positive_int_arg, metavar="M", help="deal the images to M agents")
    how.add_argument("--image-lists", nargs="+", metavar="LIST",
                     help="one text file per agent naming its images (ids, paths or file names, one per line)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="folder for agent<i>.npz (default: ./dqm-out/split)")
    outputs.add_overwrite_option(
        p, help="replace the agent*.npz files of an existing folder (those of a larger earlier split removed)")


def read_image_list(path: str, names: List[str], ids: np.ndarray) -> List[int]:
    """The image ids a list file names: an id, or an image's path or file name (matched against the
    FEATURES file's image names); InputError names the file and the line."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"--image-lists: {path} is not a file")
    by_name = {}
    for k, name in enumerate(names):
        for key in (name, Path(name).name):
            by_name.setdefault(key, []).append(k)
    present = set(np.unique(ids).tolist())
    out = []
    for lineno, raw in enumerate(p.read_text(errors="replace").splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line.lstrip("-").isdigit() and int(line) in present:
            out.append(int(line))
        elif len(by_name.get(line, ())) == 1:
            out.append(by_name[line][0])
        elif len(by_name.get(line, ())) > 1:
            raise InputError(f"{path}:{lineno}: {line!r} names several images; give the path or the id")
        else:
            raise InputError(f"{path}:{lineno}: {line!r} is not an image of the FEATURES file (an image id with "
                             "features, an image path or a file name)")
    return out


def run(args) -> int:
    from .. import io
    from ..distributed.sources import split_features
    from ..runtime.launcher import save_agent_files

    out = outputs.check_dir(args.out or outputs.default_dir("split"), "--out", AGENT_FILES, overwrite=args.overwrite,
                            default=not args.out)
    fs = io.load_features(args.features)
    agents = args.agents or len(args.image_lists)  # --image-lists: one agent a list
    LOG.info("split: %s of %s from %s over %s, whole images each", count(len(fs), "feature"),
             count(len(np.unique(fs.image_ids)), "image"), args.features, count(agents, "agent"))
    ids = np.asarray(fs.image_ids)
    n_images = len(np.unique(ids))
    lists = None
    if args.image_lists:
        names = [str(n) for n in fs.image_names] if fs.image_names is not None else []
        lists = [read_image_list(path, names, ids) for path in args.image_lists]
    elif args.agents > n_images:
        raise InputError(f"--agents {args.agents} for {n_images} images: every agent holds whole images, so at most "
                         f"{n_images} agents can have any")
    parts = split_features(fs, args.agents, lists)
    paths = save_agent_files(parts, out)
    m = len(paths)
    for stale in sorted(set(outputs.existing(out, AGENT_FILES)) - set(paths)):  # of a larger split, with --overwrite
        stale.unlink()
        print(f"removed {stale} (an earlier split's)")
    for a, (path, part) in enumerate(zip(paths, parts)):
        print(f"agent {a}: {path} ({len(np.unique(part.image_ids))} images, {len(part)} features)")
    print(f"start each agent on its host with its file, e.g.\n  dqm agent --id 0 --agents {m} --connect "
          f"tcp/ROUTER:7447 --job JOB {shlex.quote(str(paths[0]))}\nand a coordinator: dqm coordinator --agents {m} "
          "--connect tcp/ROUTER:7447 --job JOB (deploy/README.md)")
    return 0

"""Run one of the seed paper's experiments in simulation and write its report.

EXPERIMENT is currently ``localization``: the camera-network experiment
(five cameras watch a moving target; QuickMatch vs BF vs FLANN for detecting
and localizing it, see dqm/camnet/; QuickMatch also with the quadratic kernel
and online, frame by frame). It writes, in --out-dir, camnet.md (the
summary, compared with the paper's numbers) and camnet.json (every number),
and the figures in --img-dir (camnet_*.png).

    dqm experiment localization                       # docs/camnet.md, docs/img/camnet_*.png
    dqm experiment localization --seeds 0,1,2,3       # + a table over other worlds
    dqm experiment localization --quick --out-dir /tmp/cn   # 10 time steps, ~20 s
    dqm experiment localization --quick --methods quickmatch,quickmatch-online

Seeded: the same options give the same numbers.
"""
from __future__ import annotations

import logging
import sys
import time
from typing import List

from .. import outputs
from ..camnet.experiment import DEFAULT_RATIOS, DEFAULT_RHOS
from ..camnet.pipeline import DETECTION_RHO, METHODS
from ..progress import ProgressBar
from ..validation import InputError
from ..vision.baselines import DEFAULT_RATIO
from ..vision.features import PRESETS

LOG = logging.getLogger("dqm.commands")

NAME = "experiment"
HELP = "run a seed-paper experiment in simulation (localization: the camera network) and write its report"
EXPERIMENTS = ("localization",)


def _parse_list(text: str, kind, name: str) -> List:
    try:
        vals = [kind(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"{name} must be a comma-separated list of numbers, got {text!r}") from None
    if not vals:
        raise InputError(f"{name} is empty")
    return vals


def add_arguments(p) -> None:
    p.add_argument("experiment", choices=EXPERIMENTS, help="which experiment")
    p.add_argument("--out-dir", default=None,
                   help="where camnet.md and camnet.json go (default ./dqm-out/experiment; "
                        "--out-dir docs --overwrite regenerates the committed docs)")
    p.add_argument("--img-dir", default=None, help="where the figures go (default OUT_DIR/img)")
    outputs.add_overwrite_option(p, help="replace camnet.md, camnet.json and the figures of an earlier run "
                                         "(--out-dir docs --overwrite regenerates the committed docs)")
    p.add_argument("--seeds", default="0",
                   help="comma-separated world seeds; the first gets the figures, all go in a table (default 0)")
    p.add_argument("--duration", type=float, default=30.0, help="seconds of trajectory (default 30)")
    p.add_argument("--rate", type=float, default=2.0, help="frames per second (default 2)")
    p.add_argument("--cameras", type=int, default=5, help="number of cameras (default 5)")
    p.add_argument("--rho", type=float, default=DETECTION_RHO,
                   help=f"QuickMatch's rho for detection (default {DETECTION_RHO:g}; see docs/camnet.md)")
    p.add_argument("--ratio", type=float, default=DEFAULT_RATIO, help="Lowe ratio of BF / FLANN (default 0.75)")
    p.add_argument("--min-matches", type=int, default=10, help="matches for a detection (default 10)")
    p.add_argument("--ransac", type=float, default=10.0, help="RANSAC threshold in pixels (default 10)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="paper", help="SIFT settings (default paper)")
    p.add_argument("--rhos", default=",".join(f"{r:g}" for r in DEFAULT_RHOS),
                   help="QuickMatch rho values of the sweep (first seed)")
    p.add_argument("--ratios", default=",".join(f"{r:g}" for r in DEFAULT_RATIOS),
                   help="BF / FLANN ratio values of the sweep (first seed)")
    p.add_argument("--methods", default=",".join(METHODS),
                   help="comma-separated methods (default all: " + ", ".join(METHODS) + ")")
    p.add_argument("--no-sweep", action="store_true", help="skip the rho / ratio sweep (faster)")
    p.add_argument("--quick", action="store_true",
                   help="small run: 10 time steps over the same 30 s loop (rate 1/3 Hz), no sweep")
    p.add_argument("--quiet", action="store_true", help="no progress bars, no per-seed result lines")


def _command_line(argv: List[str]) -> str:
    """``dqm experiment localization`` and the options that followed it in ``argv`` (those before it, such as
    ``-v``, change only the messages)."""
    words = list(argv[1:])
    for i in range(len(words) - 1):
        if words[i:i + 2] == ["experiment", "localization"]:
            return " ".join(["dqm experiment localization", *words[i + 2:]])
    return "dqm experiment localization"


def run(args) -> int:
    from ..camnet.experiment import run_experiment
    from ..camnet.pipeline import PAPER_RHO, PipelineConfig
    from ..camnet.report import seed_row, write_report
    from ..camnet.simulator import SimConfig

    if args.experiment != "localization":  # argparse's choices already say so
        raise InputError(f"unknown experiment {args.experiment!r}")
    default = not args.out_dir
    args.out_dir = outputs.check_dir(args.out_dir or outputs.default_dir("experiment"), "--out-dir",
                                     ("camnet.md", "camnet.json"), overwrite=args.overwrite, default=default)
    if args.img_dir:
        outputs.check_dir(args.img_dir, "--img-dir", ("camnet_*.png",), overwrite=args.overwrite)
    else:
        outputs.check_dir(args.out_dir / "img", "--out-dir", ("camnet_*.png",), overwrite=args.overwrite or default)
    seeds = _parse_list(args.seeds, int, "--seeds")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    for m in methods:
        if m not in METHODS:
            raise InputError(f"--methods: unknown method {m!r}; choose from {', '.join(METHODS)}")
    if not methods or len(set(methods)) != len(methods):
        raise InputError(f"--methods must name each method at most once, got {args.methods!r}")
    if len(set(seeds)) != len(seeds):
        raise InputError(f"--seeds repeat: {args.seeds}")
    rate = 1.0 / 3.0 if args.quick else args.rate
    sweep = not (args.no_sweep or args.quick)
    rhos = _parse_list(args.rhos, float, "--rhos")
    ratios = _parse_list(args.ratios, float, "--ratios")
    if args.rho not in rhos:
        rhos = sorted(rhos + [args.rho])
    if args.ratio not in ratios:
        ratios = sorted(ratios + [args.ratio])
    pipe = PipelineConfig(preset=args.preset, rho=args.rho, ratio=args.ratio, min_matches=args.min_matches,
                          ransac_threshold=args.ransac)
    if args.quiet:  # errors only from the dqm loggers
        logging.getLogger("dqm").setLevel(logging.ERROR)
    results, rows = None, []
    t0 = time.perf_counter()
    for k, seed in enumerate(seeds):
        sim = SimConfig(seed=seed, duration=args.duration, rate=rate, n_cameras=args.cameras)
        LOG.info("seed %d: %d time steps x %d cameras", seed, sim.n_steps, sim.n_cameras)
        bar = None if args.quiet else ProgressBar(f"seed {seed}")
        # other seeds: only the headline numbers (QuickMatch at our rho and the paper's)
        res = run_experiment(sim, pipe, methods, sweep=sweep if k == 0 else True,
                             rhos=rhos if k == 0 else sorted({args.rho, PAPER_RHO}),
                             ratios=ratios if k == 0 else [args.ratio],
                             snapshot_step=-1 if k == 0 else None, progress=bar)
        if k == 0:
            results = res
        rows.append(seed_row(res))
        if not args.quiet:  # a result: standard output
            print(f"seed {seed}: " + ", ".join(f"{m} PR AUC {rows[-1]['auc'][m]:.3f}" for m in res.methods)
                  + f" ({res.timings['total']:.0f} s)", flush=True)
    written = write_report(results, args.out_dir, args.img_dir, command=_command_line(sys.argv), seed_rows=rows)
    print(f"wrote {', '.join(str(p) for p in written.values())} in {time.perf_counter() - t0:.0f} s")
    return 0

"""Run Distributed QuickMatch as separate processes on this host: a zenoh router,
M agents (each starting with the features of its own images) and the
coordinator; print the result and the traffic table.

    dqm run --agents 4                      # generated default data
    dqm run --agents 4 --features f.npz     # your FEATURES file (docs/formats.md)

It writes the job's CLUSTERS file (default ./dqm-out/run/clusters.npz: the
labels with the keypoints, image names and ground truth of the FEATURES), so
that dqm plot, dqm export and dqm evaluate work on it as on dqm match output (and dqm sfm --clusters,
with --features f.npz for the descriptors that stay with the agents).

On a terminal it shows each agent's phase, features and bytes as the job runs.
If an agent process dies, its images and cell go to the next live agent and
the job starts again (identical clusters); losing more than --max-lost agents
ends the job with a paragraph saying what failed (docs/runtime.md).

Exit codes: 0 done, 1 --check found different clusters, 2 bad input (or --out taken meanwhile by another
run or program: the result is then kept under the next free name),
3 the job failed, 4 an agent refused the job (differing parameters),
130 interrupted (Ctrl-C), 143 terminated (SIGTERM).
"""
from __future__ import annotations

import json
import logging
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .. import outputs
from ..distributed.config import DEFAULT_SEED
from ..runtime.limits import RUN, add_limits, limits_from
from ..validation import positive_int_arg
from ..wording import count
from .runtime_options import add_algorithm, config_from

LOG = logging.getLogger("dqm.commands")

NAME = "run"
HELP = "run a distributed job (router + agents + coordinator processes) on this host"


def add_arguments(p) -> None:
    p.add_argument("--agents", type=positive_int_arg, default=4, help="number of agent processes M")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED, help="partition seed integer")
    p.add_argument("--features", help="FEATURES.npz (default: a generated SIFT-like scene with ground truth)")
    p.add_argument("--out", default=None, metavar="CLUSTERS.npz",
                   help="the job's CLUSTERS file, with the keypoints and image names of the FEATURES, for dqm plot / "
                        "export / evaluate (default: ./dqm-out/run/clusters.npz)")
    p.add_argument("--report", help="also write the JSON report here (traffic per link and kind, timings, labels)")
    outputs.add_overwrite_option(p)
    p.add_argument("--check", action="store_true", help="also run the in-process simulator and compare")
    p.add_argument("--secure", action="store_true",
                   help="mutual TLS with throwaway certificates (one per process; needs openssl) and a router that "
                        "lets each process use only its own keys (dqm router --acl with the job's roster)")
    add_algorithm(p)
    add_limits(p, RUN)


#: links of the traffic table printed in full; beyond, the busiest links and the per-kind table
TABLE_LINKS = 24


def run(args) -> int:
    from .. import evaluation, io, synthetic
    from ..distributed.protocol import traffic_table
    from ..runtime.launcher import JobFailure, check_scale, run_job
    from ..validation import InputError

    out = outputs.check_file(args.out or outputs.default_dir("run") / "clusters.npz", "--out", (".npz",),
                             overwrite=args.overwrite, default=not args.out)
    if args.report:
        outputs.check_file(args.report, "--report", (".json",), overwrite=args.overwrite)
        outputs.check_distinct(("--out", out), ("--report", args.report))
    limits = limits_from(args)
    if args.features:
        fs = io.load_features(args.features)
    else:
        ds = synthetic.sift_like(n_images=8, n_points=500, noise=0.35, seed=0)
        fs = io.FeatureSet(ds.descriptors, ds.image_ids, point_ids=ds.point_ids)
    X, ids, truth = fs.descriptors, fs.image_ids, fs.point_ids
    n_images = len(np.unique(ids))
    if len(X) == 0 or n_images < 2:
        raise InputError(f"a distributed job needs features of at least two images, got {n_images}")
    cfg = config_from(args, args.agents, args.seed).validated(len(X), runtime=True)
    limits = limits.but(ready_timeout_s=check_scale(cfg.agents, n_images, limits.ready_timeout_s))
    LOG.info("job %r: %s of %s (%s); starting a zenoh router, %s and a coordinator on this host, %s mode",
             cfg.job, count(len(X), "feature"), count(n_images, "image"),
             args.features or "a generated scene with ground truth",
             count(cfg.agents, "agent process", "agent processes"), cfg.mode)
    LOG.debug("algorithm: %s", cfg.params_text())
    t0 = time.perf_counter()
    # the coordinator writes the CLUSTERS file into a folder of this run's own beside --out; this process then
    # takes the name (dqm.outputs.publish): a run started meanwhile, or a file put there, is not replaced
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".staging", dir=out.parent))
    taken = None
    try:
        try:
            rep = run_job(X, ids, cfg, limits, progress=True, features=fs, clusters=str(staging / out.name),
                          secure=args.secure)
        except JobFailure as exc:
            print(f"dqm run: {exc}", file=sys.stderr)
            return 4 if exc.failure.get("refused") else 3
        try:
            out = outputs.publish(staging / out.name, out)
        except outputs.OutputTaken as exc:  # the result is kept under another name: the report still follows
            taken, out = exc, outputs.written(out)
        rep["clusters_file"] = str(out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    wall = time.perf_counter() - t0
    labels = np.asarray(rep["labels"])
    sizes = np.bincount(labels)
    mode = rep.get("mode", cfg.mode)
    if "auto" in rep:
        from ..runtime.coordinator import auto_summary

        print(auto_summary(rep["auto"]))
    print(f"Distributed QuickMatch ({mode} mode, {cfg.agents} agent processes, partition {cfg.partition}, "
          f"seed {cfg.seed}): {len(labels)} features from {n_images} images -> {rep['clusters']} clusters, "
          f"{int((sizes > 1).sum())} spanning 2+ images; {wall:.1f} s wall.")
    for lost in rep.get("lost", []):
        print(f"Agent process {lost['process']} was lost in phase {lost['phase']}; its agents were taken over "
              f"(owners now {rep['owners']}) and the job restarted at epoch {lost['epoch'] + 1}.")
    if truth is not None and (np.asarray(truth) >= 0).any():
        s = evaluation.cluster_scores_landmarks(labels, np.asarray(truth), ids)
        print(f"Against ground truth: precision {s.precision:.3f}, recall {s.recall:.3f}, F1 {s.f1:.3f}.")
    cpu = {int(a): st.get("cpu_s", 0.0) for a, st in rep.get("per_agent", {}).items()}
    if mode == "gather":
        print(f"Work: agent 0 matched every feature itself in {rep.get('match_s', 0.0):.2f} s (dqm.quickmatch); "
              f"the other agents sent it their features ({sum(cpu.values()):.2f} CPU s in all).")
    elif cpu:
        busiest = max(cpu, key=cpu.get)
        pairs = [st.get("pairs", 0.0) for st in rep["per_agent"].values()]
        most = 100.0 * max(pairs) / max(1.0, len(labels) * (len(labels) - 1) / 2)
        share = f"; the most pairs at one agent: {most:.0f}% of the centralized pass" if any(pairs) else ""
        print(f"Work: the busiest agent (agent {busiest}) used {cpu[busiest]:.2f} CPU s, all agents "
              f"{sum(cpu.values()):.2f} CPU s{share}.")
    raw = np.asarray(X).size * (1 if np.asarray(X).dtype == np.uint8 else 4)
    probes = rep["auto"]["probe_bytes"] if "auto" in rep else 0
    print(f"Traffic: {rep['total_bytes']} bytes metered ({rep['total_bytes'] / raw:.2f}x the raw descriptor bytes)"
          + (f", {rep['wire_bytes_received_by_router']} bytes received by the router (kernel TCP counters"
             + (f"; --mode auto's link probes, {probes} bytes, among them" if probes else "") + ")"
             if rep.get("wire_bytes_received_by_router") else "") + ".")
    print(traffic_table(rep, max_links=TABLE_LINKS))
    if len(rep["links"]) > TABLE_LINKS:
        print(f"(the {TABLE_LINKS} busiest of {len(rep['links'])} links; every link is in "
              + (f"{args.report})" if args.report else "the report: --report FILE)"))
    if args.report:  # before the check: a long check must not put the job's result at risk
        outputs.write_text(args.report, json.dumps(rep))
        print(f"wrote {args.report}")
    if rep.get("images_note"):
        print(f"Images: {rep['images_note']}.")
    drawable = fs.keypoints is not None and fs.image_names is not None
    named = shlex.quote(str(out))  # the hint is a command line to paste: a path with spaces quoted
    print(f"wrote {out} (CLUSTERS" + (f": dqm plot clusters {named} --out clusters.png, dqm export colmap {named} ..."
                                      if drawable else f": dqm plot sizes {named} --out sizes.png") + ")")
    if args.check:
        from ..distributed.simulator import simulate

        # gather ran dqm.quickmatch: check it against balanced's simulation (its clusters with the quadratic
        # kernel and the exact engine), or against dqm.quickmatch itself with another kernel or the fast engine
        central = mode == "gather" and (cfg.kernel != "quadratic" or cfg.engine != "exact")
        what, name = (("dqm.quickmatch in this process", "dqm.quickmatch") if central
                      else ("the in-process simulator", "In-process simulator"))
        print(f"Checking: the same job ({len(labels)} features, {cfg.agents} agents, {mode} mode) in {what}; this "
              "takes about as long as the job's CPU time ...", file=sys.stderr, flush=True)
        t1 = time.perf_counter()
        if central:
            import dqm

            reference = dqm.quickmatch(X, ids, params=cfg.params, engine=cfg.engine).labels
        else:
            reference = simulate(X, ids, cfg.but(mode="balanced" if mode == "gather" else mode)).labels
        same = np.array_equal(reference, labels)
        print(f"{name}: {'identical clusters' if same else 'DIFFERENT clusters'} "
              f"({time.perf_counter() - t1:.1f} s).")
        if not same:
            return 1
    if taken is not None:
        print(f"dqm run: error: {taken}", file=sys.stderr)
        return 2
    return 0

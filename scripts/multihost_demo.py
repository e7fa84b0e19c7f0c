#!/usr/bin/env python3
"""Distributed QuickMatch across several "hosts" on this machine (network namespaces).

Builds a router namespace and 2-3 host namespaces joined to it by veth pairs
(private subnet 10.213.0.0/16, nothing leaves the machine), runs `dqm router`
in the router namespace, spreads the agents over the hosts (agent a on host
a mod H, the coordinator on host 1), checks that the clusters equal the
in-process simulator's, prints the traffic report and compares the metered
bytes with the kernel's counters on the veths, then deletes the namespaces.

    sudo .venv/bin/python scripts/multihost_demo.py                 # 4 agents on 3 hosts
    sudo .venv/bin/python scripts/multihost_demo.py --agents 6 --hosts 2 --points 500
    sudo .venv/bin/python scripts/multihost_demo.py --features my.npz --keep out/multihost
    sudo .venv/bin/python scripts/multihost_demo.py --tls          # mutual TLS (certificates by openssl)
    sudo .venv/bin/python scripts/multihost_demo.py --tls --acl    # and the router enforces the job's roster

Needs root (ip netns). Exit code 0: identical clusters; 1: different; 2: cannot run here.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dqm import io, synthetic
from dqm.distributed import DQMConfig, simulate
from dqm.distributed.protocol import traffic_table
from dqm.runtime.launcher import work_folder
from dqm.runtime.multihost import (
    Namespaces,
    NamespacesUnavailable,
    make_certs,
    netns_unavailable_reason,
    run_across_namespaces,
)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--agents", type=int, default=4)
    p.add_argument("--hosts", type=int, default=3, choices=range(1, 10), metavar="H", help="host namespaces (1-9)")
    p.add_argument("--seed", type=int, default=1, help="partition seed integer")
    p.add_argument("--features", help="FEATURES.npz (default: generated SIFT-like scene)")
    p.add_argument("--images", type=int, default=6)
    p.add_argument("--points", type=int, default=200)
    p.add_argument("--partition", default="kmeans", choices=["kmeans", "seeded"])
    p.add_argument("--job", default="multihost")
    p.add_argument("--timeout", type=float, default=120.0)
    p.add_argument("--keep", help="keep the agents' files and logs in this folder")
    p.add_argument("--tls", action="store_true", help="mutual TLS on every link (certificates made with openssl)")
    p.add_argument("--acl", action="store_true",
                   help="with --tls: the router enforces the job's roster (each process only its own keys)")
    args = p.parse_args(argv)
    if args.acl and not args.tls:
        p.error("--acl needs --tls (identities are the certificates' common names)")

    reason = netns_unavailable_reason()
    if reason:
        print(f"multihost_demo: cannot run here: {reason}", file=sys.stderr)
        return 2
    if args.features:
        fs = io.load_features(args.features)
        X, ids = fs.descriptors, fs.image_ids
    else:
        ds = synthetic.sift_like(n_images=args.images, n_points=args.points, seed=0)
        X, ids = ds.descriptors, ds.image_ids
    cfg = DQMConfig(agents=args.agents, seed=args.seed, partition=args.partition, job=args.job).validated(len(X))
    t0 = time.perf_counter()
    try:
        with work_folder(args.keep, "dqm-multihost-") as wd:
            certs = None
            if args.tls:
                router_names = [Namespaces(hosts=args.hosts).router_addr(h) for h in range(args.hosts)]
                certs = make_certs(wd / "certs", router_names,
                                   [f"agent{a}" for a in range(cfg.agents)] + ["coordinator"])
                print(f"  certificates (CA, router naming {', '.join(router_names)}, clients) in {certs}")
            res = run_across_namespaces(X, ids, cfg, wd, hosts=args.hosts, timeout_s=args.timeout, tls_certs=certs,
                                        acl=args.acl, log=lambda t: print(f"  {t}", flush=True))
    except NamespacesUnavailable as exc:
        print(f"multihost_demo: cannot run here: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        print(f"multihost_demo: {exc}", file=sys.stderr)
        return 1
    wall = time.perf_counter() - t0
    rep = res.report
    labels = np.asarray(rep["labels"])
    sim = simulate(X, ids, cfg)
    same = np.array_equal(sim.labels, labels)
    print(f"\n{len(labels)} features of {len(np.unique(ids))} images, {cfg.agents} agents on {args.hosts} hosts"
          f"{' over mutual TLS' if args.tls else ''}{' with access control' if args.acl else ''}: "
          f"{rep['clusters']} clusters; {wall:.1f} s wall including namespace set-up "
          f"(job {rep['wall_s']:.1f} s). Simulator: {'identical clusters' if same else 'DIFFERENT clusters'}.")
    print(f"Namespaces {', '.join(res.namespaces)} deleted.\n")
    print(traffic_table(rep))
    print("\n| host | metered sent | kernel host->router | ratio | metered received | kernel router->host | ratio |")
    print("|---|---|---|---|---|---|---|")
    met = res.metered_per_host()
    for h, c in res.counters.items():
        m = met[h]
        print(f"| h{h + 1} | {m['sent']} | {c['rx_bytes']} | {c['rx_bytes'] / max(1, m['sent']):.3f} "
              f"| {m['received']} | {c['tx_bytes']} | {c['tx_bytes'] / max(1, m['received']):.3f} |")
    k = res.kernel_totals()
    print(f"| total | {rep['total_bytes']} | {k['to_router']} | {k['to_router'] / rep['total_bytes']:.3f} "
          f"| {rep['total_bytes']} | {k['from_router']} | {k['from_router'] / rep['total_bytes']:.3f} |")
    print("\n(kernel bytes include Ethernet/IP/TCP headers, TCP acks, zenoh framing, handshakes and keep-alives"
          + (", TLS records" if args.tls else "") + ")")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())

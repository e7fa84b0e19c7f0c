"""Options shared by the runtime commands (algorithm parameters, TLS)."""
from __future__ import annotations

from typing import Optional

from ..core.clustering import DEFAULT_RHO, KERNELS
from ..core.distributed import DQM_MODES, DQMConfig
from ..core.partition import PARTITION_MODES


def add_algorithm(p) -> None:
    g = p.add_argument_group("algorithm (must be the same for every agent of a job)")
    g.add_argument("--mode", choices=DQM_MODES, default="default", help="default (improved) or paper (literal)")
    g.add_argument("--partition", choices=PARTITION_MODES, default="kmeans")
    g.add_argument("--rho", type=float, default=DEFAULT_RHO)
    g.add_argument("--kernel", choices=KERNELS, default="quadratic")
    g.add_argument("--halo", type=float, default=1.0, help="contested-test width factor (1 = safe)")
    g.add_argument("--samples", type=int, default=64, help="k-means sample descriptors per agent")
    g.add_argument("--seed-norm", type=float, default=512.0, help="descriptor norm for seeded seeds (SIFT: 512)")
    g.add_argument("--job", default="job", help="job id; keeps concurrent jobs on one router apart")


def config_from(args, agents: int, seed: int = 0) -> DQMConfig:
    return DQMConfig(agents=agents, seed=seed, partition=args.partition, mode=args.mode, rho=args.rho,
                     kernel=args.kernel, samples_per_agent=args.samples, halo=args.halo,
                     seed_norm=args.seed_norm, job=args.job)


def add_tls(p) -> None:
    g = p.add_argument_group("mutual TLS (use tls/HOST:PORT endpoints)")
    g.add_argument("--tls-ca", help="root CA certificate (PEM)")
    g.add_argument("--tls-cert", help="this process's certificate (PEM)")
    g.add_argument("--tls-key", help="this process's private key (PEM)")


def tls_from(args, listen: bool) -> Optional[dict]:
    if not (args.tls_ca or args.tls_cert or args.tls_key):
        return None
    from ..validation import InputError

    if not (args.tls_ca and args.tls_cert and args.tls_key):
        raise InputError("mutual TLS needs all of --tls-ca, --tls-cert and --tls-key")
    side = "listen" if listen else "connect"
    return {"root_ca_certificate": args.tls_ca, f"{side}_certificate": args.tls_cert,
            f"{side}_private_key": args.tls_key, "enable_mtls": True}

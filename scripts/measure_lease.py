#!/usr/bin/env python
"""How fast a lost host is noticed: cut a client's link and time its liveliness token's loss.

Needs root and network namespaces (dqm.runtime.multihost). A router namespace and two
"hosts": host 1 holds a liveliness token, host 2 watches it; then host 1's link is set
down (no FIN, no RST: a pulled cable) and the watcher reports when the token vanished.
With the runtime's lease (dqm.runtime.bus.LEASE_MS) this is the detection time on a LAN.

    sudo .venv/bin/python scripts/measure_lease.py --repeat 4
"""
import argparse
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dqm.runtime.bus import LEASE_MS  # noqa: E402
from dqm.runtime.launcher import Processes  # noqa: E402
from dqm.runtime.multihost import Namespaces, _ip, netns_unavailable_reason  # noqa: E402

HOLDER = """import sys, time
from dqm.runtime.bus import open_client
s = open_client(sys.argv[1]); t = s.liveliness().declare_token("dqm/lease/alive/agent/0")
print("holding", flush=True); time.sleep(60)"""
WATCHER = """import sys, time
from dqm.runtime.bus import open_client
s = open_client(sys.argv[1])
sub = s.liveliness().declare_subscriber("dqm/lease/alive/**", lambda x: print(x.kind, time.time(), flush=True),
                                        history=True)
time.sleep(60)"""


def once(workdir: Path) -> float:
    with Namespaces(hosts=2, tag="lease") as nss:
        procs = Processes()
        try:
            procs.start(["router", "--listen", f"tcp/{nss.router_addr(0)}:7447", "--listen",
                         f"tcp/{nss.router_addr(1)}:7447"], workdir / "router.log", prefix=nss.prefix(nss.router_ns))
            time.sleep(2)
            w = subprocess.Popen(nss.prefix(nss.host_ns(1)) + [sys.executable, "-c", WATCHER,
                                                               f"tcp/{nss.router_addr(1)}:7447"],
                                 stdout=subprocess.PIPE, text=True, cwd=ROOT)
            h = subprocess.Popen(nss.prefix(nss.host_ns(0)) + [sys.executable, "-c", HOLDER,
                                                               f"tcp/{nss.router_addr(0)}:7447"],
                                 stdout=subprocess.PIPE, text=True, cwd=ROOT)
            h.stdout.readline()
            w.stdout.readline()  # the token appeared at the watcher
            time.sleep(1)
            t_down = time.time()
            _ip("-n", nss.host_ns(0), "link", "set", "eth0", "down")
            line = w.stdout.readline().split()
            for p in (h, w):
                p.kill()
                p.wait()
            return float(line[1]) - t_down
        finally:
            procs.stop_all()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default="dqm-out/measure_lease", help="folder for the router's log")
    args = ap.parse_args(argv)
    why = netns_unavailable_reason()
    if why:
        print(f"cannot measure here: {why}")
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    times = [once(out) for _ in range(args.repeat)]
    print(f"lease {LEASE_MS} ms: a cut link was noticed after " + ", ".join(f"{t:.2f}" for t in times) + " s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

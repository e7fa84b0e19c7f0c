#!/usr/bin/env python3
"""A hostile but admitted client against a live dqm job behind a router with access control.

Starts a `dqm router --acl ROSTER` over mutual TLS on loopback, runs a balanced job of
--agents agent processes and a coordinator with one certificate each, holds agent 0 at
a state for the attack window, and meanwhile plays two attackers:

* **mallory**: a second client holding the certificate of the job's last agent (a robot
  of the team that was compromised): admitted, with that agent's rights;
* **outsider**: a client with a certificate of the same CA whose name is in no roster line.

Each of them subscribes to the other processes' inboxes and to ``dqm/**``; puts forged
``start`` / ``go`` / ``abort`` / ``finish`` / ``result`` / ``ready`` messages with fresh
sequence numbers as the coordinator and as the other agents, on their keys and on its
own; replays the real messages mallory receives on its own inbox; declares the others'
liveliness tokens. It counts what the attackers received and what the job accepted:
every forged message that reaches a process must be refused there (the job's rejection
counters account for each), the labels must equal the in-process simulator's, the job
must run in one epoch with no process lost, and no forged token may be visible.

Then it checks that no certificate, a certificate of another CA, an expired certificate,
and a username with a wrong password (a router with --users) are refused.

    .venv/bin/python scripts/attack.py                      # 3 agents, 3 s of attacks, table on stdout
    .venv/bin/python scripts/attack.py --json attack.json --write-doc   # also update docs/runtime.md

Exit code 0: every attack failed; 1: one got through; 2: cannot run here (no openssl).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dqm import synthetic
from dqm.distributed import DQMConfig, keys, messages, simulate
from dqm.runtime.bus import RouterUnreachable, client_config, open_client
from dqm.runtime.launcher import (
    Processes,
    client_tls,
    finish_job,
    free_port,
    make_certs,
    start_job,
    tls_options,
    write_agent_files,
)
from dqm.runtime.multihost import start_router

DOC = Path(__file__).resolve().parents[1] / "docs" / "runtime.md"
BEGIN, END = "<!-- attack table: begin -->", "<!-- attack table: end -->"
CONTROL_KINDS = ("start", "go", "abort", "finish")
AGENT_KINDS = ("result", "ready", "refuse")


def expired_cert(certs: Path, name: str) -> None:
    """``name``.pem/.key signed by the CA in ``certs``, expired since yesterday."""
    key, csr, pem = (certs / f"{name}.{x}" for x in ("key", "csr", "pem"))
    run = lambda *a: subprocess.run(a, check=True, capture_output=True)  # noqa: E731
    run("openssl", "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(key))
    run("openssl", "req", "-new", "-key", str(key), "-out", str(csr), "-subj", f"/CN={name}")
    run("openssl", "x509", "-req", "-in", str(csr), "-CA", str(certs / "ca.pem"), "-CAkey", str(certs / "ca.key"),
        "-CAcreateserial", "-out", str(pem), "-days", "-1")
    csr.unlink()


def forged(job: str, kind: str, src: int, epoch: int, rng: np.random.Generator, agents: int) -> bytes:
    """A well-formed message of ``kind`` claiming to come from ``src``, with a fresh sequence number."""
    seq = int(rng.integers(1 << 20, 1 << 40))
    fields = {
        "start": dict(seed=99, agents=agents, owners=np.zeros(agents, np.int64), params="x", params_hash="0" * 64,
                      catalog=0),
        "go": {}, "abort": dict(reason="forged abort"), "finish": dict(clusters=1),
        "result": dict(ids=np.arange(3, dtype=np.int64), labels=np.zeros(3, np.int64)),
        "ready": dict(dim=128, dtype="|u1", hosted=np.array([src], np.int64), features=3),
        "refuse": dict(reason="forged refusal", param=""),
    }[kind]
    return messages.encode(kind, job, src, seq=seq, epoch=epoch, **fields)


class Spy:
    """A session that subscribes to what it must not read; counts bytes of messages not addressed to
    its own process (``own``: that process's key prefix, or None)."""

    def __init__(self, session, exprs, own):
        self.bytes = 0
        self.samples = 0
        self.keys = Counter()
        self.own = own
        self._lock = threading.Lock()
        self.subs = [session.declare_subscriber(e, self._on) for e in exprs]

    def _on(self, sample):
        key = str(sample.key_expr)
        if self.own and key.startswith(self.own):
            return
        with self._lock:
            self.bytes += len(sample.payload.to_bytes())
            self.samples += 1
            self.keys[key.split("/from/")[0]] += 1

    def close(self):
        for s in self.subs:
            s.undeclare()


def open_attackers(endpoint: str, certs: Path, job: str, m: int) -> dict:
    """Both attackers' sessions, their spying subscriptions and mallory's capture of its own inbox,
    opened before the job starts so that they see all of it."""
    evil = m - 1  # mallory holds the certificate of the job's last agent
    victims = [-1] + [a for a in range(m) if a != evil]
    spy_exprs = ["dqm/**", f"dqm/{job}/**", f"dqm/{job}/proc/*/from/*/**"] + [
        keys.process_inbox(job, v) for v in victims] + [f"dqm/{job}/proc/{keys.process_name(v)}/**" for v in victims]
    out: dict = {"sent": Counter(), "own_key_sent": 0, "subscriptions": len(spy_exprs)}
    sessions = {}
    for who, name in (("mallory", f"agent{evil}"), ("outsider", "outsider")):
        sessions[who] = [open_client(endpoint, client_tls(certs, name)) for _ in range(3)]  # spy, forger, capture
    spies = {"mallory": Spy(sessions["mallory"][0], spy_exprs, keys.message_key(job, 0, evil, evil).split("/from/")[0]),
             "outsider": Spy(sessions["outsider"][0], spy_exprs, None)}
    captured = []
    cap = sessions["mallory"][2].declare_subscriber(
        keys.process_inbox(job, evil), lambda s: captured.append((str(s.key_expr), bytes(s.payload.to_bytes()))))
    out.update(_sessions=sessions, _spies=spies, _captured=captured, _cap=cap)
    return out


def attack_window(out: dict, job: str, m: int, seconds: float, rng) -> dict:
    """Both attackers at once for ``seconds``; returns what they sent, received and got admitted."""
    evil = m - 1
    victims = [-1] + [a for a in range(m) if a != evil]
    sessions, spies, captured, cap = (out.pop(k) for k in ("_sessions", "_spies", "_captured", "_cap"))
    out["_sessions"] = sessions
    tokens = out["_tokens"] = []
    import zenoh

    block = zenoh.CongestionControl.BLOCK  # the default (DROP) would lose puts: then nothing could be counted
    for who in ("mallory", "outsider"):
        for key in (keys.alive_coordinator(job), keys.alive_agent(job, 0), keys.alive_agent(job, m),
                    keys.alive_stream(job), keys.alive_coordinator(job + "-other")):
            tokens.append(sessions[who][1].liveliness().declare_token(key))
            out["sent"][f"{who}: liveliness token of another"] += 1
    time.sleep(0.3)
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        for who in ("mallory", "outsider"):
            s = sessions[who][1]
            own = evil if who == "mallory" else m + 7  # the outsider has no process; it claims one
            for v in victims:
                for epoch in (0, 1):
                    for kind in CONTROL_KINDS:  # as the coordinator: on its key, and on the attacker's own
                        payload = forged(job, kind, -1, epoch, rng, m)
                        s.put(keys.message_key(job, -1, v, v), payload, congestion_control=block)
                        s.put(keys.message_key(job, own, v, v), payload, congestion_control=block)
                        out["sent"][f"{who}: as the coordinator, on its key"] += 1
                        out["sent"][f"{who}: as the coordinator, on the attacker's key"] += 1
                        out["own_key_sent"] += who == "mallory"
                    for a in range(m):
                        if a == evil:
                            continue
                        for kind in AGENT_KINDS:  # as another agent: on its key, and on the attacker's own
                            payload = forged(job, kind, a, epoch, rng, m)
                            s.put(keys.message_key(job, a, v, v), payload, congestion_control=block)
                            s.put(keys.message_key(job, own, v, v), payload, congestion_control=block)
                            out["sent"][f"{who}: as another agent, on its key"] += 1
                            out["sent"][f"{who}: as another agent, on the attacker's key"] += 1
                            out["own_key_sent"] += who == "mallory"
            if who == "mallory":  # replay what reached its own inbox, on the original key and on its own
                for key, raw in [c for c in captured if keys.parse_message_key(job, c[0])][:20]:
                    src = keys.parse_message_key(job, key)[0]
                    for v in victims:
                        s.put(keys.message_key(job, src, v, v), raw, congestion_control=block)
                        s.put(keys.message_key(job, evil, v, v), raw, congestion_control=block)
                        out["sent"][f"{who}: replayed, on the original sender's key"] += 1
                        out["sent"][f"{who}: replayed, on the attacker's key"] += 1
                        out["own_key_sent"] += 1
        time.sleep(0.2)
    time.sleep(1.0)  # let the last puts arrive and be counted before the job resumes
    out["captured"] = len(captured)
    out["sent"] = dict(out["sent"])
    out["received"] = {who: {"bytes": sp.bytes, "messages": sp.samples, "keys": dict(sp.keys)}
                       for who, sp in spies.items()}
    for sp in spies.values():
        sp.close()
    cap.undeclare()
    return out


def refused(endpoint: str, tls, deadline_s: float = 2.0) -> tuple:
    """(refused?, seconds): whether a client with these settings cannot open a session."""
    t0 = time.monotonic()
    try:
        s = open_client(endpoint, tls, deadline_s=deadline_s)
    except RouterUnreachable:
        return True, time.monotonic() - t0
    s.close()
    return False, time.monotonic() - t0


def refusals(wd: Path, certs: Path, other: Path, endpoint: str) -> dict:
    """Connection attempts that the router must refuse; and a username router for the password case."""
    expired_cert(certs, "expired")
    rows = {
        "no certificate": {"root_ca_certificate": str(certs / "ca.pem"), "enable_mtls": True},
        "certificate of another CA": client_tls(other, "intruder"),
        "expired certificate": client_tls(certs, "expired"),
    }
    users = wd / "users.txt"
    users.write_text("coordinator:right-password\n")
    roster = wd / "user-roster.txt"
    roster.write_text("coordinator coordinator\n")
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    procs = Processes()
    try:
        start_router(procs, [ep], wd, ("127.0.0.1", port), tls_args=["--users", str(users), "--acl", str(roster)],
                     log_name="user-router.log")
        tries = [(endpoint, tls) for tls in rows.values()] + [(ep, {"usrpwd": {"user": "coordinator",
                                                                               "password": "wrong"}})]
        names = list(rows) + ["username with a wrong password"]
        with ThreadPoolExecutor(len(tries)) as pool:  # each waits out its retry deadline: at once, not in turn
            out = dict(zip(names, pool.map(lambda t: refused(*t), tries)))
        ok, took = refused(ep, {"usrpwd": {"user": "coordinator", "password": "right-password"}})
        out["(control) username with the right password"] = (ok, took)
    finally:
        procs.stop_all()
    return out


def markdown(res: dict) -> str:
    a = res["attack"]
    rows = ["| attack | tried | what got through |", "|---|---:|---|"]
    for who in ("mallory", "outsider"):
        r = a["received"][who]
        rows.append(f"| {who}: subscribe to the other processes' inboxes, `dqm/**`, `dqm/{res['job']}/**` | "
                    f"{a['subscriptions']} subscriptions | {r['bytes']} bytes of others' messages received |")
    for what, n in sorted(a["sent"].items()):
        if what.endswith("liveliness token of another"):
            got = f"none visible to the observer ({res['forged_tokens_visible']} forged tokens in all)"
        elif what.startswith("outsider"):
            got = "0: the router drops them (an identity in no roster line may do nothing)"
        elif "attacker's key" in what:
            got = "reached the processes, all refused there (counted below)"
        else:
            got = "0: the router drops them (not the sender's key)"
        rows.append(f"| {what.replace(': ', ': forged, ', 1)} | {n} | {got} |")
    rows.append(f"| forged messages on mallory's own keys | {a['own_key_sent']} | {res['rejected_total']} refused "
                f"by the job's processes, **{res['accepted']} accepted** |")
    rows.append(f"| the job | 1 | labels identical to the simulator: **{res['labels_identical']}**, "
                f"{res['epochs']} epoch, {len(res['lost'])} processes lost |")
    for name, (ok, took) in res["refusals"].items():
        rows.append(f"| connect with {name} | 1 | {'refused' if ok else 'admitted'} ({took:.1f} s) |")
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--agents", type=int, default=3)
    p.add_argument("--images", type=int, default=6)
    p.add_argument("--points", type=int, default=200)
    p.add_argument("--seconds", type=float, default=3.0, help="length of the attack window")
    p.add_argument("--json", help="write the results here")
    p.add_argument("--write-doc", action="store_true", help=f"put the table into {DOC.name} between its markers")
    p.add_argument("--keep", help="keep the work folder (certificates, logs) here")
    args = p.parse_args(argv)
    if shutil.which("openssl") is None:
        print("attack.py: cannot run here: openssl is not installed (it makes the certificates)", file=sys.stderr)
        return 2
    m = args.agents
    if m < 2:
        p.error("--agents must be at least 2 (mallory holds one agent's certificate)")
    wd = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="dqm-attack-"))
    wd.mkdir(parents=True, exist_ok=True)
    job = "attacked"
    rng = np.random.default_rng(0)
    ds = synthetic.sift_like(n_images=args.images, n_points=args.points, seed=0)
    cfg = DQMConfig(agents=m, seed=1, job=job).validated(len(ds.descriptors))
    files = write_agent_files(ds.descriptors, ds.image_ids, m, wd)
    certs = make_certs(wd / "certs", ["127.0.0.1"], ["coordinator", "outsider", "observer"]
                       + [f"agent{a}" for a in range(m)])
    other = make_certs(wd / "other-ca", ["127.0.0.1"], ["intruder"])
    roster = wd / "roster.txt"
    roster.write_text("coordinator coordinator\n" + "".join(f"agent agent{a} {a}\n" for a in range(m))
                      + "viewer observer\n")
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    marker = wd / "paused"
    env = dict(os.environ, DQM_FAULT_PAUSE="0:wait_bounds", DQM_FAULT_MARKER=str(marker), DQM_FAULT_SECONDS="60")
    procs = Processes()
    res: dict = {"job": job, "agents": m, "features": int(len(ds.descriptors)), "seconds": args.seconds}
    attack = attackers = side = None
    try:
        start_router(procs, [endpoint], wd, ("127.0.0.1", port),
                     tls_args=[*tls_options(certs, "router"), "--acl", str(roster)])
        import zenoh

        observer = zenoh.open(client_config(endpoint, client_tls(certs, "observer")))
        attackers = open_attackers(endpoint, certs, job, m)
        job_run = start_job(procs, cfg, files, wd, connect=lambda a: endpoint,
                            client_args=lambda a: tls_options(certs, "coordinator" if a < 0 else f"agent{a}"),
                            env=env)
        t0 = time.monotonic()
        while not marker.exists() and time.monotonic() - t0 < 60:
            if job_run.coordinator.poll() is not None:
                break
            time.sleep(0.05)
        if not marker.exists():
            raise RuntimeError("the job never reached the attack window (see the logs in " + str(wd) + ")")
        attack = attack_window(attackers, job, m, args.seconds, rng)
        marker.unlink()
        side = ThreadPoolExecutor(1)  # the connection attempts beside the rest of the job: the router is up
        refused_later = side.submit(refusals, wd, certs, other, endpoint)
        rep = finish_job(job_run, 120.0)
        time.sleep(0.5)
        legit = {keys.alive_agent(job, a) for a in range(m)} | {keys.alive_coordinator(job)}
        visible = {str(r.ok.key_expr) for r in observer.liveliness().get("dqm/**", timeout=2.0) if r.ok is not None}
        observer.close()
        res["forged_tokens_visible"] = len(visible)  # the job's processes have exited: any token left is forged
        res["tokens_left"] = sorted(visible - legit) + sorted(visible & legit)
        sim = simulate(ds.descriptors, ds.image_ids, cfg)
        res["labels_identical"] = bool(np.array_equal(np.asarray(rep["labels"]), sim.labels))
        res["epochs"], res["lost"] = rep["epochs"], rep["lost"]
        res["rejected"] = rep["rejected"]
        res["rejected_total"] = int(sum(rep["rejected"].values()))
        res["accepted"] = attack["own_key_sent"] - res["rejected_total"]
        res["refusals"] = refused_later.result()
    finally:
        if attackers is not None:  # a session left open hangs the interpreter at exit
            for t in attackers.pop("_tokens", []):
                t.undeclare()
            for ss in attackers.pop("_sessions", {}).values():
                for s in ss:
                    s.close()
        if side is not None:  # the connection attempts end within seconds, the router up or not
            side.shutdown()
        procs.stop_all()
    res["attack"] = {k: v for k, v in attack.items() if not k.startswith("_")}
    ok = (all(r["bytes"] == 0 for r in res["attack"]["received"].values()) and res["accepted"] == 0
          and res["labels_identical"] and res["epochs"] == 1 and not res["lost"]
          and res["forged_tokens_visible"] == 0
          and all(v[0] for k, v in res["refusals"].items() if not k.startswith("(control)"))
          and not res["refusals"]["(control) username with the right password"][0])
    res["ok"] = ok
    table = markdown(res)
    print(table)
    print(f"\nattack.py: {'every attack failed' if ok else 'AN ATTACK GOT THROUGH'}; {m} agents, "
          f"{res['features']} features, {args.seconds:g} s of attacks")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1, default=str))
    if args.write_doc:
        text = DOC.read_text()
        if BEGIN not in text or END not in text:
            print(f"attack.py: {DOC} has no {BEGIN} ... {END} markers", file=sys.stderr)
            return 2
        head, rest = text.split(BEGIN, 1)
        _, tail = rest.split(END, 1)
        given = argv if argv is not None else sys.argv[1:]
        cmd = " ".join(["scripts/attack.py"] + [x for i, x in enumerate(given)
                                                if x != "--json" and (i == 0 or given[i - 1] != "--json")])
        DOC.write_text(f"{head}{BEGIN}\nMade by `{cmd}` ({m} agents, {res['features']} features, "
                       f"{args.seconds:g} s of attacks, eclipse-zenoh {zenoh_version()}):\n\n{table}\n{END}{tail}")
    if not args.keep:
        shutil.rmtree(wd, ignore_errors=True)
    return 0 if ok else 1


def zenoh_version() -> str:
    from importlib.metadata import version

    return version("eclipse-zenoh")


if __name__ == "__main__":
    sys.exit(main())

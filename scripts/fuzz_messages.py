#!/usr/bin/env python
"""Fuzz a live distributed job with random, mutated and replayed messages.

A job (3 agent processes, balanced mode, generated data) is started; agent 0 is
held in the middle of the protocol (the ghost round) while a foreign zenoh client
that has recorded the job's real traffic so far puts ``--messages`` hostile
messages on the agents' and the coordinator's inboxes:

* random bytes; real messages cut short;
* wrong types (a field replaced by a value of another type);
* huge sizes (over the agents' size limit, or arrays whose shape claims far more than they hold);
* wrong epoch (later, negative), wrong job id, wrong version, unknown kind, bad sender;
* replays of real messages, verbatim.

Then agent 0 is released and the job must finish with labels identical to the
in-process simulator, no process may crash, and every hostile message must be
accounted for: refused and counted by reason, or dropped as a duplicate (a replay
of a numbered message), or harmless (a replayed acknowledgement or progress report).

    python scripts/fuzz_messages.py                     # 10,000 messages -> ./dqm-out/fuzz_messages/
    python scripts/fuzz_messages.py --messages 500      # the small version CI runs
"""
import argparse
import json
import os
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dqm.distributed import DQMConfig, keys, messages, simulate  # noqa: E402
from dqm.runtime.launcher import run_job  # noqa: E402
from dqm.runtime.limits import RuntimeLimits  # noqa: E402
from dqm.synthetic import sift_like  # noqa: E402

LIMIT = 1 << 21  # the agents' --max-message-bytes in this job
CATEGORIES = ("random", "truncated", "wrong_type", "huge", "wrong_epoch", "wrong_job", "bad_header", "replayed")
HEADER = messages.HEADER


def mutate(category: str, rng: np.random.Generator, captured, job: str, m: int):
    """One hostile message: (key, payload, expected fate) with fate 'refused', 'duplicate' or 'harmless'."""
    inboxes = [keys.message_key(job, 0, a, a) for a in range(m)] + [keys.message_key(job, 0, -1, -1)]
    if category == "random":
        return inboxes[rng.integers(len(inboxes))], rng.bytes(int(rng.integers(0, 300))), "refused"
    key, raw = captured[rng.integers(len(captured))]
    body = messages.unpack_body(raw)
    if category == "truncated":
        return key, raw[:int(rng.integers(0, len(raw)))], "refused"
    if category == "replayed":
        harmless = body["kind"] in messages.UNNUMBERED
        return key, raw, "harmless" if harmless else "duplicate"
    if category == "wrong_type":
        fields = [f for f in body if f not in HEADER]
        if not fields:
            body["seq"] = "x"
        else:
            f = fields[rng.integers(len(fields))]
            v = body[f]
            body[f] = "x" if isinstance(v, (int, float, dict, list, bytes)) or v is None else 12345
    elif category == "huge":
        if rng.random() < 0.05:
            return key, b"\x91" + b"\x00" * (LIMIT + int(rng.integers(1, 1 << 16))), "refused"
        arrays = [f for f, v in body.items() if isinstance(v, dict) and {"dtype", "shape", "data"} <= set(v)]
        if arrays:
            f = arrays[rng.integers(len(arrays))]
            body[f] = dict(body[f], shape=[1 << 39] + list(body[f]["shape"][1:]))
        else:
            body["v"] = 1 << 40
    elif category == "wrong_epoch":
        body["epoch"] = -1 if rng.random() < 0.2 else int(body["epoch"]) + int(rng.integers(1, 1000))
        if body["kind"] == "start":  # a later start would be legitimate (a restart): keep it invalid
            body["epoch"] = -1
    elif category == "wrong_job":
        body["job"] = "another-job"
    elif category == "bad_header":
        which = rng.integers(4)
        if which == 0:
            body["v"] = messages.VERSION + 1
        elif which == 1:
            body["kind"] = "nonsense"
        elif which == 2:
            body["src"] = m + int(rng.integers(0, 100))
        else:
            body["seq"] = -int(rng.integers(1, 100))
    return key, messages.pack_body(body), "refused"


def fuzz(port: int, job: str, m: int, n: int, seed: int, marker: Path, result: dict) -> None:
    import zenoh

    from dqm.runtime.bus import open_client

    session = open_client(f"tcp/127.0.0.1:{port}")
    captured = []
    lock = threading.Lock()

    def on_sample(sample):
        raw = bytes(sample.payload.to_bytes())
        if len(raw) <= 64 << 10:  # replays of small messages only (a replayed 0.5 MB chunk proves nothing more)
            with lock:
                captured.append((str(sample.key_expr), raw))

    sub = session.declare_subscriber(f"dqm/{job}/**", on_sample)
    try:
        t0 = time.monotonic()
        while not marker.exists() and time.monotonic() - t0 < 120:
            time.sleep(0.02)
        time.sleep(0.3)
        sub.undeclare()
        sub = None
        with lock:
            pool = list(captured)
        rng = np.random.default_rng(seed)
        fates = Counter()
        per_category = Counter()
        t1 = time.monotonic()
        for i in range(n):
            cat = CATEGORIES[i % len(CATEGORIES)]
            key, payload, fate = mutate(cat, rng, pool, job, m)
            session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
            fates[fate] += 1
            per_category[cat] += 1
        result.update(sent=n, fates=dict(fates), per_category=dict(per_category), captured=len(pool),
                      seconds=time.monotonic() - t1)
        time.sleep(1.0)  # let the receivers count everything before agent 0 goes on
    finally:
        if sub is not None:
            sub.undeclare()
        session.close()
        marker.unlink(missing_ok=True)  # release agent 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--messages", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="dqm-out/fuzz_messages", help="output folder")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ds = sift_like(n_images=6, n_points=200, clutter_per_image=80, noise=0.3, seed=5)
    X, ids = ds.descriptors, ds.image_ids
    m = 3
    cfg = DQMConfig(agents=m, seed=2, job=f"fuzz-{os.getpid()}")
    marker = out / f"paused-{os.getpid()}"
    marker.unlink(missing_ok=True)
    env = dict(os.environ, DQM_FAULT_PAUSE="0:wait_ghost", DQM_FAULT_MARKER=str(marker), DQM_FAULT_SECONDS="600")
    fz: dict = {}
    threads = []

    def on_started(info):
        th = threading.Thread(target=fuzz, args=(info["port"], cfg.job, m, args.messages, args.seed, marker, fz),
                              daemon=True)
        th.start()
        threads.append(th)

    t0 = time.monotonic()
    try:
        rep = run_job(X, ids, cfg, RuntimeLimits(job_timeout_s=900), env=env, on_started=on_started,
                      agent_args=["--max-message-bytes", str(LIMIT), "--phase-timeout", "900"])
    except RuntimeError as exc:
        print(f"the job failed under fuzzing: {exc}")
        return 1
    identical = bool(np.array_equal(np.asarray(rep["labels"]), simulate(X, ids, cfg).labels))
    rejected = {k: int(v) for k, v in sorted(rep["rejected"].items(), key=lambda kv: -kv[1])}
    duplicates = int(rep.get("duplicates", 0))
    crashes = sum(1 for c in rep["agent_exit_codes"] if c != 0)
    summary = {"messages": fz.get("sent", 0), "seconds_to_send": round(fz.get("seconds", 0.0), 2),
               "expected": fz.get("fates", {}), "per_category": fz.get("per_category", {}),
               "refused_by_reason": rejected, "refused_total": sum(rejected.values()), "duplicates": duplicates,
               "labels_identical": identical, "crashes": crashes, "agent_exit_codes": rep["agent_exit_codes"],
               "job_seconds": round(time.monotonic() - t0, 1)}
    (out / "fuzz_messages.json").write_text(json.dumps(summary, indent=1))
    exp = summary["expected"]
    print(f"{summary['messages']} hostile messages in {summary['seconds_to_send']} s "
          f"({', '.join(f'{k} {v}' for k, v in summary['per_category'].items())})")
    print(f"labels identical to the simulator: {identical}; crashes: {crashes}")
    print(f"refused and counted: {summary['refused_total']} (expected {exp.get('refused', 0)}); duplicates dropped: "
          f"{duplicates} (expected at least {exp.get('duplicate', 0)}); harmless replays (acks, progress): "
          f"{exp.get('harmless', 0)}")
    print("| reason | count |\n|---|---|")
    for k, v in rejected.items():
        print(f"| {k} | {v} |")
    ok = (identical and crashes == 0 and summary["refused_total"] == exp.get("refused", 0)
          and duplicates >= exp.get("duplicate", 0))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

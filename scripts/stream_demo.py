#!/usr/bin/env python3
"""Streaming demo: camera processes put the simulator's frames at 2 Hz into `dqm stream`.

Starts, on this host, a zenoh router, a `dqm stream` process and one process per
camera of the camera-network simulator (dqm.camnet.simulator). Every camera
process renders its frames, extracts SIFT (dqm.vision.features) and puts one
`image` message per frame on dqm/<job>/stream/images at --rate Hz (image id =
camera * 10^9 + frame, as dqm camera numbers them; the frame is saved as a PNG
whose path is the image's name; the cameras are staggered within a period), once
the stream's liveliness token is present. This script also puts --bad malformed
messages, which the stream must reject, count and survive, and listens to the
change sets on dqm/<job>/stream/changes.

At the end it checks that the stream's final clusters (its --out CLUSTERS file)
equal batch dqm.quickmatch(kernel="quadratic") on the same images in arrival
order (with --window: the images still in the window), and that the published
events replayed from an empty assignment give them too, and that the file names
every image (image_names, so that `dqm plot clusters` can draw it); it prints the
latency of every image (camera put -> change set received here) and the counts.

    python scripts/stream_demo.py                         # 3 cameras x 12 frames, about 15 s
    python scripts/stream_demo.py --cameras 5 --frames 40 --window 30
    python scripts/stream_demo.py --keep dqm-out/stream_demo   # keep the logs and the CLUSTERS file

Every child dies with this script (dqm.runtime.lifeline). Exit code 0: identical
clusters; 1: different (or the stream failed); 2: cannot run here.
"""
from __future__ import annotations

import argparse
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dqm.distributed import keys, messages  # noqa: E402
from dqm.runtime.stream import camera_image_id, split_image_id, wait_for_token  # noqa: E402

BAD_KINDS = ("garbage", "nan", "version", "job", "dimension", "duplicate")


# ---------------------------------------------------------------------- camera node (a child process)
def camera_node(args) -> int:
    """Render this camera's frames, extract SIFT, put one image message per frame at the slot times."""
    import cv2
    import zenoh

    from dqm.camnet.simulator import SimConfig, build_world
    from dqm.runtime.bus import open_client
    from dqm.runtime.lifeline import watch_parent
    from dqm.vision import features

    watch_parent()
    c, n_cams, wd = args.camera_node, args.cameras, Path(args.workdir)
    log = lambda text: print(f"[camera {c}] {text}", flush=True)  # noqa: E731
    world = build_world(SimConfig(seed=args.seed, n_cameras=n_cams, duration=args.frames / args.rate,
                                  rate=args.rate))
    session = open_client(args.connect)
    sent = []
    try:
        if not wait_for_token(session, keys.alive_stream(args.job), 60.0):
            log("the stream never appeared")
            return 1
        (wd / f"cam{c}.ready").write_text("ready\n")
        go = wd / "go"
        while not go.exists():
            time.sleep(0.02)
        start = float(go.read_text())
        key = keys.camera_images(args.job, c)
        descs, ids, kps = [], [], []
        late = 0
        for f in range(world.n_steps):
            slot = start + f / args.rate + c / (args.rate * n_cams)
            wait = slot - time.time()
            if wait > 0:
                time.sleep(wait)
            else:
                late += 1
            img, truth = world.render(c, f)
            feats = features.extract(img, max_features=args.max_features)
            image_id = camera_image_id(c, f)
            png = wd / f"cam{c}_frame{f:03d}.png"  # named by its path: dqm plot can draw the stream's result
            cv2.imwrite(str(png), img)
            payload = messages.image_message(args.job, c, image_id, feats.descriptors, feats.keypoints, seq=f,
                                             name=str(png.resolve()))
            session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
            sent.append(image_id)
            descs.append(feats.descriptors)
            ids.append(np.full(len(feats), image_id, np.int64))
            kps.append(feats.keypoints)
            seen = "seen" if truth.visible else "not seen"
            log(f"frame {f}: image {image_id}, {len(feats)} features, target {seen}, {len(payload)} bytes")
        np.savez(wd / f"cam{c}.npz", descriptors=np.concatenate(descs), image_ids=np.concatenate(ids),
                 keypoints=np.concatenate(kps))
        log(f"done: {len(sent)} frames put ({late} behind their slot)")
        time.sleep(0.3)
        return 0
    finally:
        session.close()


# ---------------------------------------------------------------------- the demo (parent)
def bad_message(kind: str, job: str, dim: int, seen_image: int) -> bytes:
    rng = np.random.default_rng(len(kind))
    d = rng.integers(0, 255, size=(20, dim)).astype(np.uint8)
    if kind == "garbage":
        return b"\x00not a message\xff" + rng.bytes(40)
    if kind == "nan":
        f = d.astype(np.float32)
        f[3, 7] = np.nan
        return messages.image_message(job, 99, 10 ** 9 + 1, f)
    if kind == "version":
        body = messages.unpack_body(messages.image_message(job, 99, 10 ** 9 + 2, d))
        body["v"] = messages.VERSION + 1
        return messages.pack_body(body)
    if kind == "job":
        return messages.image_message("another-job", 99, 10 ** 9 + 3, d)
    if kind == "dimension":
        return messages.image_message(job, 99, 10 ** 9 + 4, d[:, : dim // 2])
    return messages.image_message(job, 99, seen_image, d)  # duplicate: an image id the stream already has


WORKDIR_PREFIX = "dqm-stream-demo-"


def remove_stale_workdirs() -> None:
    """Remove the temporary folders of demos that were killed outright (their pid no longer runs)."""
    for d in Path(tempfile.gettempdir()).glob(WORKDIR_PREFIX + "*"):
        try:
            os.kill(int(d.name[len(WORKDIR_PREFIX):].split("-")[0]), 0)
        except ProcessLookupError:
            shutil.rmtree(d, ignore_errors=True)
        except (ValueError, PermissionError):
            pass


def start_child(procs, argv, log_path: Path):
    """A child process that dies with this one (as dqm.runtime.launcher starts its children)."""
    from dqm.runtime.lifeline import PARENT_ENV, child_preexec

    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env[PARENT_ENV] = str(os.getpid())
    with open(log_path, "w") as fh:
        p = subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True,
                             preexec_fn=child_preexec(os.getpid()))
    procs.procs.append(p)
    return p


def percentile_line(values_ms) -> str:
    v = np.asarray(values_ms)
    if not len(v):
        return "no latencies"
    return (f"p50 {np.percentile(v, 50):.0f} ms, p90 {np.percentile(v, 90):.0f} ms, max {v.max():.0f} ms "
            f"(mean {v.mean():.0f} ms) over {len(v)} images")


def main(argv=None) -> int:  # noqa: C901 - a demo's steps in order
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cameras", type=int, default=3, help="camera processes (default 3)")
    p.add_argument("--frames", type=int, default=12, help="frames per camera (default 12: 6 s at 2 Hz)")
    p.add_argument("--rate", type=float, default=2.0, help="frames per second per camera (default 2)")
    p.add_argument("--window", type=int, default=None, help="the stream's --window (images kept)")
    p.add_argument("--rho", type=float, default=0.9)
    p.add_argument("--max-features", type=int, default=400, help="SIFT features per frame (default 400)")
    p.add_argument("--seed", type=int, default=0, help="simulator seed")
    p.add_argument("--bad", type=int, default=len(BAD_KINDS), help="malformed messages to put (default 6)")
    p.add_argument("--job", default="stream-demo")
    p.add_argument("--keep", help="keep the logs and the CLUSTERS file in this folder")
    p.add_argument("--camera-node", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--connect", help=argparse.SUPPRESS)
    p.add_argument("--workdir", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.camera_node is not None:
        return camera_node(args)
    if args.cameras < 1 or args.frames < 1 or not args.rate > 0 or (args.window is not None and args.window < 1):
        p.error("--cameras, --frames, --rate and --window must be positive")
    try:
        import zenoh
    except ImportError:
        print("stream_demo: cannot run here: eclipse-zenoh is not installed", file=sys.stderr)
        return 2
    from dqm.runtime.launcher import Processes, free_port, wait_listening

    remove_stale_workdirs()
    wd = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix=f"{WORKDIR_PREFIX}{os.getpid()}-"))
    wd.mkdir(parents=True, exist_ok=True)
    for stale in list(wd.glob("cam*")) + [wd / "go", wd / "clusters.npz"]:  # cam*.ready, .npz, .log, _frame*.png
        stale.unlink(missing_ok=True)
    total = args.cameras * args.frames
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    procs = Processes()
    session = None
    received = []  # (receipt time, decoded changes message)
    inbox: "queue.Queue" = queue.Queue()
    t_start = time.perf_counter()
    failed = 0
    first = threading.Event()

    last_rx = [time.monotonic()]

    def on_changes(sample) -> None:
        inbox.put((time.time(), bytes(sample.payload.to_bytes())))
        last_rx[0] = time.monotonic()
        first.set()

    def on_sigterm(signum, frame):
        raise KeyboardInterrupt

    old_term = signal.signal(signal.SIGTERM, on_sigterm)
    try:
        router = start_child(procs, [sys.executable, "-m", "dqm", "router", "--listen", endpoint], wd / "router.log")
        wait_listening("127.0.0.1", port, 15.0, router)
        from dqm.runtime.bus import open_client

        session = open_client(endpoint)
        sub = session.declare_subscriber(keys.stream_changes(args.job), on_changes)
        stream_args = [sys.executable, "-m", "dqm", "stream", "--connect", endpoint, "--job", args.job,
                       "--rho", repr(args.rho), "--images", str(total), "--idle", "120",
                       "--out", str(wd / "clusters.npz"), "--verbose"]
        if args.window:
            stream_args += ["--window", str(args.window)]
        stream = start_child(procs, stream_args, wd / "stream.log")
        if not wait_for_token(session, keys.alive_stream(args.job), 60.0):
            raise RuntimeError("the stream did not come up within 60 s")
        cams = [start_child(procs, [sys.executable, str(Path(__file__).resolve()), "--camera-node", str(c),
                                    "--cameras", str(args.cameras), "--frames", str(args.frames), "--rate",
                                    repr(args.rate), "--max-features", str(args.max_features), "--seed",
                                    str(args.seed), "--job", args.job, "--connect", endpoint, "--workdir", str(wd)],
                            wd / f"camera{c}.log")
                for c in range(args.cameras)]
        t0 = time.monotonic()
        while not all((wd / f"cam{c}.ready").exists() for c in range(args.cameras)):
            if any(cp.poll() is not None for cp in cams) or time.monotonic() - t0 > 120:
                raise RuntimeError("a camera process failed to start (see its log)")
            time.sleep(0.05)
        start = time.time() + 0.3
        (wd / "go.tmp").write_text(repr(start))
        os.replace(wd / "go.tmp", wd / "go")
        print(f"router {endpoint}, stream and {args.cameras} camera processes up after "
              f"{time.perf_counter() - t_start:.1f} s; streaming {args.frames} frames per camera at {args.rate:g} Hz",
              flush=True)
        # malformed messages, spread over the stream once it has its first image (and so its dimension)
        bad_sent = Counter()
        first.wait(timeout=60)
        t_bad = time.time()
        for b in range(max(0, args.bad)):
            kind = BAD_KINDS[b % len(BAD_KINDS)]
            time.sleep(max(0.0, t_bad + b / (2 * args.rate) - time.time()))
            session.put(keys.camera_images(args.job, 99), bad_message(kind, args.job, 128, 0),
                        congestion_control=zenoh.CongestionControl.BLOCK)
            bad_sent[kind] += 1
        deadline = start + args.frames / args.rate + 120
        for cp in cams:
            cp.wait(timeout=max(1.0, deadline - time.time()))
        # the stream ends by itself after the last image; while it catches up, change sets keep coming
        t_cams = time.monotonic()
        while stream.poll() is None and time.monotonic() - max(last_rx[0], t_cams) < 15:
            time.sleep(0.1)
        if stream.poll() is None:  # no change set for 15 s: an image went missing; stopped, it still writes --out
            stream.send_signal(signal.SIGTERM)
        rc = stream.wait(timeout=60)
        time.sleep(0.3)
        sub.undeclare()
    except KeyboardInterrupt:
        print("stream_demo: interrupted", file=sys.stderr)
        failed = 130
    except (RuntimeError, subprocess.TimeoutExpired) as exc:
        print(f"stream_demo: {exc}; logs in {wd}", file=sys.stderr)
        args.keep = args.keep or str(wd)  # keep the logs of a failure
        failed = 1
    finally:
        signal.signal(signal.SIGTERM, old_term)
        if session is not None:
            session.close()
        procs.stop_all()  # before the folder goes: the children write into it
    if failed:
        if not args.keep:
            shutil.rmtree(wd, ignore_errors=True)
        return failed
    try:
        return report(args, wd, inbox, received, rc, bad_sent, total, time.perf_counter() - t_start)
    finally:
        if not args.keep:
            shutil.rmtree(wd, ignore_errors=True)


def report(args, wd: Path, inbox, received, rc: int, bad_sent: Counter, total: int, wall: float) -> int:
    import dqm
    from dqm import io
    from dqm.core.events import EVENT_KINDS, replay

    while not inbox.empty():
        t, raw = inbox.get()
        received.append((t, messages.decode(raw, job=args.job)))
    received.sort(key=lambda tm: tm[1]["seq"])
    stream_log = (wd / "stream.log").read_text(errors="replace")
    summary = [ln for ln in stream_log.splitlines() if ln.startswith(("stream (", "  ", "wrote", "[stream] rejected"))]
    print("\nthe stream's log ends with:\n" + "\n".join("  | " + ln for ln in summary))
    if rc != 0 or not (wd / "clusters.npz").exists():
        print(f"stream_demo: the stream exited with code {rc}; logs in {wd}", file=sys.stderr)
        return 1
    # what the cameras sent, and what the stream kept (arrival order, minus the window's removals)
    names = {m["image_id"]: m["name"] for _, m in received if m["op"] == "add"}
    sent = {}
    for c in range(args.cameras):
        z = np.load(wd / f"cam{c}.npz")
        for i in np.unique(z["image_ids"]):
            sel = z["image_ids"] == i
            sent[int(i)] = z["descriptors"][sel]
    arrival = [m["image_id"] for _, m in received if m["op"] == "add"]
    removed = {m["image_id"] for _, m in received if m["op"] == "remove"}
    present = [i for i in arrival if i not in removed]
    # latency: the camera's put (its clock) -> this process received the change set of that add
    lat = {m["image_id"]: (t - m["time"]) * 1e3 for t, m in received if m["op"] == "add"}
    print(f"\n{'image':>10} {'camera':>6} {'frame':>5} {'features':>8} {'events':>6} {'latency':>9}")
    for _, m in received:
        if m["op"] != "add":
            continue
        i = m["image_id"]
        cam, frame = split_image_id(i)
        print(f"{i:>10} {cam:>6} {frame:>5} {len(m['added']):>8} {len(m['event_kind']):>6} {lat[i]:>6.0f} ms")
    events = Counter()
    for _, m in received:
        for k in m["event_kind"]:
            events[EVENT_KINDS[int(k)]] += 1
    last = received[-1][1] if received else None
    # the checks
    cl = io.load_clusters(wd / "clusters.npz")
    X = np.concatenate([sent[i] for i in present])
    ids = np.concatenate([np.full(len(sent[i]), i, np.int64) for i in present])
    # the file numbers the present images 0..K-1 in arrival order; params stream_image_ids maps them back
    file_ids = np.concatenate([np.full(len(sent[i]), k, np.int64) for k, i in enumerate(present)])
    same_input = (np.array_equal(cl["descriptors"], X) and np.array_equal(cl["image_ids"], file_ids)
                  and cl["params"].get("stream_image_ids") == present)
    named = "image_names" in cl and cl["image_names"].tolist() == [names[i] for i in present]
    batch = dqm.quickmatch(X, ids, rho=args.rho, kernel="quadratic")
    same = same_input and np.array_equal(cl["labels"], batch.labels)
    assignment = {}
    for _, m in received:
        replay(assignment, messages.changes_events(m))
    order = sorted(assignment)
    from dqm.core.tree import canonical_labels

    replayed = np.array_equal(canonical_labels(np.array([assignment[k] for k in order], np.int64)), cl["labels"])
    print(f"\nlatency (camera put -> change set received): {percentile_line(list(lat.values()))}")
    print(f"images: {total} put by {args.cameras} cameras, {len(arrival)} accepted, {len(removed)} removed by the "
          f"window, {len(present)} present; {len(X)} features, {batch.n_clusters} clusters "
          f"({int((batch.cluster_sizes() >= 2).sum())} with 2+ features)")
    print(f"malformed messages put: {sum(bad_sent.values())} ({', '.join(f'{k} {v}' for k, v in bad_sent.items())}); "
          f"rejected by the stream: {last['rejected'] if last else 0}")
    print(f"change sets received: {len(received)} ({len(arrival)} adds, {len(removed)} removals); events: "
          + (", ".join(f"{events[k]} {k}" for k in EVENT_KINDS if events[k]) or "none"))
    print(f"final clusters vs batch dqm.quickmatch(kernel='quadratic') on the {len(present)} images: "
          f"{'IDENTICAL' if same else 'DIFFERENT'}; events replayed from scratch give the same clusters: "
          f"{'yes' if replayed else 'NO'}")
    print(f"the CLUSTERS file names every image (image_names): {'yes' if named else 'NO'}")
    print(f"{wall:.1f} s in all" + (f"; logs, frames and clusters.npz in {wd} (draw it: dqm plot clusters "
                                    f"{wd / 'clusters.npz'} --out clusters.png)" if args.keep else ""))
    ok = (same and replayed and named and len(arrival) == total
          and (last is None or last["rejected"] == sum(bad_sent.values())))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

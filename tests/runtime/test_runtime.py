"""The multi-process runtime on this host: equality with the simulator, metering, faults, bad messages."""
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from runtime_helpers import job_data

from dqm.distributed import DQMConfig, keys, messages, simulate
from dqm.runtime.launcher import run_job
from dqm.runtime.limits import RuntimeLimits

pytest.importorskip("zenoh")


@pytest.fixture(scope="module")
def data():
    return job_data()


@pytest.mark.parametrize("mode,partition,engine", [("balanced", "kmeans", "exact"), ("balanced", "seeded", "exact"),
                                                   ("lean", "kmeans", "exact"), ("balanced", "kmeans", "fast"),
                                                   ("balanced", "kmeans", "auto")])
def test_runtime_equals_simulator_and_meters_traffic(data, mode, partition, engine):
    X, ids = data
    cfg = DQMConfig(agents=3, seed=2, partition=partition, mode=mode, job=f"eq-{mode}-{partition}-{engine}",
                    engine=engine)
    rep = run_job(X, ids, cfg, RuntimeLimits(job_timeout_s=120))
    sim = simulate(X, ids, cfg)
    np.testing.assert_array_equal(np.asarray(rep["ids"]), np.arange(len(X)))
    np.testing.assert_array_equal(np.asarray(rep["labels"]), sim.labels)
    assert rep["engine"] == sim.config.engine == cfg.engine_for(len(X))  # auto: the coordinator's go named it
    assert rep["agent_exit_codes"] == [0, 0, 0]
    # metered bytes against the kernel's TCP counters of the router's sockets
    wire = rep["wire_bytes_received_by_router"]
    assert wire is not None and wire > 0
    assert abs(rep["total_bytes"] - wire) / wire < 0.10, (rep["total_bytes"], wire)
    # the runtime sent exactly the messages the simulator metered, kind by kind, byte for byte
    # (the agents' timing reports to the coordinator are the only messages the simulator leaves out)
    sim_kinds = sim.traffic.per_kind()
    run_kinds = {k: (v["bytes"], v["messages"]) for k, v in rep["kinds"].items() if k not in ("stats", "progress")}
    assert run_kinds == sim_kinds
    assert rep["kinds"]["stats"]["messages"] == 3
    links = {(e["src"], e["dst"]) for e in rep["links"]}
    assert ("coordinator", "agent0") in links and ("agent2", "coordinator") in links
    if mode == "balanced":
        assert all(st["consistency_failures"] == 0 for st in rep["per_agent"].values())


def test_a_gather_job_matches_with_the_jobs_engine(data):
    import dqm

    X, ids = data
    for engine in ("fast", "exact"):
        cfg = DQMConfig(agents=3, seed=2, mode="gather", job=f"gather-{engine}", engine=engine)
        rep = run_job(X, ids, cfg, RuntimeLimits(job_timeout_s=120))
        np.testing.assert_array_equal(np.asarray(rep["labels"]),
                                      dqm.quickmatch(X, ids, kernel="quadratic", engine=engine).labels)
        # the gathering agent says which engine matched (the quadratic kernel's clusters are the same here)
        gatherer = [st for st in rep["per_agent"].values() if "match_s" in st]
        assert len(gatherer) == 1 and gatherer[0]["fast_engine"] == float(engine == "fast"), rep["per_agent"]


def test_runtime_agrees_sigma_of_single_feature_images(data):
    """Images with one feature take the median sigma of all agents' features (the fill rounds)."""
    import dqm

    X, ids = data
    X = np.vstack([X, X[:1] // 2, X[5:6]])
    ids = np.concatenate([ids, [100, 101]])
    cfg = DQMConfig(agents=3, seed=4, job="fill")
    rep = run_job(X, ids, cfg, RuntimeLimits(job_timeout_s=120))
    sim = simulate(X, ids, cfg)
    np.testing.assert_array_equal(np.asarray(rep["labels"]), sim.labels)
    np.testing.assert_array_equal(sim.labels, dqm.quickmatch(X, ids, kernel="quadratic").labels)
    assert rep["kinds"]["fill"]["messages"] == 2 and rep["kinds"]["sigmas"]["messages"] == 2
    assert {k: (v["bytes"], v["messages"]) for k, v in rep["kinds"].items()
            if k not in ("stats", "progress")} == sim.traffic.per_kind()


def test_no_router_gives_a_clear_error(tmp_path):
    from dqm.runtime.launcher import free_port, write_agent_files

    X = np.random.default_rng(0).integers(0, 255, size=(20, 128)).astype(np.uint8)
    f = write_agent_files(X, np.repeat([0, 1], 10), 1, tmp_path)[0]
    port = free_port()
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "dqm", "agent", "--id", "0", "--agents", "1", "--connect",
                        f"tcp/127.0.0.1:{port}", "--connect-timeout", "1", str(f)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    assert f"no zenoh router reachable at tcp/127.0.0.1:{port}" in p.stderr
    assert time.monotonic() - t0 < 30


def _inject(endpoint, job, agents, dim, ready, marker=None, done=None):
    """A foreign client that sends hostile messages to every agent's inbox (then deletes ``marker``: the
    paused agent goes on), and keeps its session open until ``done`` is set (the job is over)."""
    import zenoh

    from dqm.runtime.bus import open_client

    s = open_client(endpoint)
    seen = set()
    watcher = s.liveliness().declare_subscriber(keys.alive_all(job), lambda smp: seen.add(str(smp.key_expr)),
                                                history=True)
    try:
        t0 = time.monotonic()
        while not all(keys.alive_agent(job, a) in seen for a in range(agents)) and time.monotonic() - t0 < 30:
            time.sleep(0.02)
        good = dict(phase="route", seq=999999, ids=np.arange(2, dtype=np.int64), image_ids=np.zeros(2, np.int64),
                    sigma=np.ones(2), unit=np.zeros(2, np.int64))
        bad = [
            messages.encode("features", job, 1, descriptors=np.zeros((2, dim), np.uint8), **good),  # as agent 1
            messages.encode("abort", job, -1, reason="forged"),  # as the coordinator
            b"\x00garbage\xff",
            messages.encode("finish", job, -1, clusters=1).replace(
                b"\xa1v" + bytes([messages.VERSION]), b"\xa1v\x7f"),
            messages.encode("features", job, 0, descriptors=np.zeros((2, dim // 2), np.uint8), **good),
            messages.encode("features", "another-job", 0, descriptors=np.zeros((2, dim), np.uint8), **good),
            b"\x91" + b"\x00" * (3 << 20),  # larger than the agents' limit (last: the slowest to deliver)
        ]
        ready.set()
        for payload in bad:
            for a in range(agents):
                # on process 0's keys (without access control the router lets anyone put there)
                s.put(keys.message_key(job, 0, a, a), payload, congestion_control=zenoh.CongestionControl.BLOCK)
        # let the 3 MiB puts arrive and be counted before the paused agent goes on: each agent reports its
        # counters once, when its own part is acknowledged, so a put counted after that is not in the report (13
        # of 14 counted once in a CI run on 2 busy cores with 1 s here; not reproduced alone, nor beside 6 busy
        # processes: the cause is a guess, and the assertion below now names the counts)
        time.sleep(3.0)
    finally:
        if marker is not None:  # once the agent is paused (it writes the marker then)
            t0 = time.monotonic()
            while not marker.exists() and time.monotonic() - t0 < 30:
                time.sleep(0.02)
            marker.unlink(missing_ok=True)
        # Closing the session while a 3 MiB put was still leaving dropped it (13 of 14 counted, in two CI runs
        # with a 1 s wait): the session stays open until the job is over.
        if done is not None:
            done.wait(150)
        watcher.undeclare()
        s.close()


def test_hostile_messages_are_rejected_and_counted(data, tmp_path):
    X, ids = data
    cfg = DQMConfig(agents=2, seed=3, job="hostile")
    marker = tmp_path / "paused"  # agent 0 waits in wait_start until the injector is done (60 s at most)
    env = dict(os.environ, DQM_FAULT_PAUSE="0:wait_start", DQM_FAULT_MARKER=str(marker), DQM_FAULT_SECONDS="60")
    ready, done = threading.Event(), threading.Event()

    def on_started(info):
        threading.Thread(target=_inject, args=(f"tcp/127.0.0.1:{info['port']}", cfg.job, 2, X.shape[1], ready,
                                               marker, done), daemon=True).start()

    try:
        rep = run_job(X, ids, cfg, RuntimeLimits(job_timeout_s=120), env=env, on_started=on_started,
                      agent_args=["--max-message-bytes", str(1 << 21)])
    finally:
        done.set()
    assert ready.is_set()
    np.testing.assert_array_equal(np.asarray(rep["labels"]), simulate(X, ids, cfg).labels)
    rejected = {}
    for st in rep["per_agent"].values():
        for k, v in st.items():
            if k.startswith("rejected:"):
                rejected[k] = rejected.get(k, 0) + v
    text = " ".join(rejected)
    assert "not valid msgpack" in text
    assert "schema version" in text
    assert "descriptor dimension" in text
    assert "another-job" in text
    assert "exceeds the maximum" in text
    assert "message of agent N on the key of process N, which does not host it" in text
    assert "abort message of the coordinator on the key of process N" in text
    assert sum(rejected.values()) >= 7 * 2, rejected


def test_sigterm_to_dqm_run_leaves_no_process(tmp_path):
    marker = tmp_path / "paused"
    env = dict(os.environ, DQM_FAULT_PAUSE="0:wait_bounds", DQM_FAULT_MARKER=str(marker))
    p = subprocess.Popen([sys.executable, "-m", "dqm", "run", "--agents", "2", "--job", "sigterm-test"],
                         env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    t0 = time.monotonic()
    while not marker.exists() and time.monotonic() - t0 < 60:
        time.sleep(0.05)
    assert marker.exists()
    p.send_signal(signal.SIGTERM)
    p.wait(timeout=30)
    time.sleep(0.5)
    left = subprocess.run(["pgrep", "-f", "job sigterm-test"], capture_output=True, text=True).stdout.split()
    assert left == [], f"processes left behind: {left}"

"""`dqm coordinator --also-agent`: the coordinator's host runs agent 0 in a process forked from the
coordinator's once its imports are done (one interpreter start there instead of two: issue 39, item 4).
The job's clusters are those of separately started agents; the forked agent dies with the coordinator;
bad agent options are the coordinator's one-line error, before any work."""
import os
import shlex
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from runtime_helpers import alive

import dqm
from dqm import io, synthetic
from dqm.cli import main
from dqm.distributed import DQMConfig
from dqm.runtime.launcher import ForkedAgent, Processes, free_port, write_agent_files
from dqm.runtime.multihost import finish_job, start_job, start_router

pytest.importorskip("zenoh")


def processes_with(*words):
    """Running processes (zombies aside) whose command line holds every one of ``words``: a forked process
    keeps its parent's command line."""
    found = []
    for entry in os.listdir("/proc"):
        try:
            with open(f"/proc/{entry}/cmdline", "rb") as fh:
                args = fh.read().decode(errors="replace").split("\0")
        except (OSError, ValueError):
            continue
        if entry.isdigit() and all(w in args for w in words) and alive(int(entry)):
            found.append(int(entry))
    return found


@pytest.mark.parametrize("mode", ["balanced", "auto"])
def test_agent_forked_from_the_coordinator_gives_the_centralized_clusters(tmp_path, mode):
    ds = synthetic.sift_like(n_images=6, n_points=150, clutter_per_image=60, noise=0.3, seed=5)
    expected = dqm.quickmatch(ds.descriptors, ds.image_ids, kernel="quadratic").labels
    cfg = DQMConfig(agents=3, seed=1, job=f"forked-{mode}", mode=mode)
    files = write_agent_files(ds.descriptors, ds.image_ids, 3, tmp_path)
    port = free_port()
    procs = Processes()
    try:
        start_router(procs, [f"tcp/127.0.0.1:{port}"], tmp_path, ("127.0.0.1", port))
        job = start_job(procs, cfg, files, tmp_path, connect=lambda a: f"tcp/127.0.0.1:{port}",
                        threads_per_agent=None, agent0_in_coordinator=True)
        assert isinstance(job.agents[0], ForkedAgent) and len(procs.procs) == 1 + 2 + 1  # router, coord, agents 1-2
        # the coordinator's host has the longest start (agent 0 is forked from it): it is started first
        assert procs.procs[1:] == [job.coordinator, *job.agents[1:]]
        seen = []
        while job.coordinator.poll() is None and not seen:  # the coordinator and the agent it forked
            seen = [pid for pid in processes_with("coordinator", f"--job=forked-{mode}") if pid != job.coordinator.pid]
            time.sleep(0.02)
        rep = finish_job(job, 90)
        left = [pid for pid in seen if alive(pid)]
    finally:
        procs.stop_all()
    assert rep["agent_exit_codes"] == [None, 0, 0]
    order = np.argsort(rep["ids"])
    np.testing.assert_array_equal(np.asarray(rep["labels"])[order], expected)
    assert (tmp_path / "agent0.log").exists() and "Traceback" not in (tmp_path / "agent0.log").read_text()
    assert "exited with code" not in (tmp_path / "coordinator.log").read_text()
    assert len(seen) == 1 and left == []  # the forked agent ran, and has exited with its coordinator


def test_the_forked_agent_dies_with_the_coordinator(tmp_path):
    """Agent 1 never starts, so the job waits for it; SIGKILL of the coordinator ends the forked agent 0."""
    ds = synthetic.sized(2_000)
    files = write_agent_files(ds.descriptors, ds.image_ids, 2, tmp_path)
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    procs = Processes()
    try:
        start_router(procs, [endpoint], tmp_path, ("127.0.0.1", port))
        agent = shlex.join(["--id", "0", "--agents", "2", "--connect", endpoint, "--job", "orphan", str(files[0])])
        coord = subprocess.Popen([sys.executable, "-m", "dqm", "coordinator", "--agents", "2", "--connect", endpoint,
                                  "--job", "orphan", "--no-clusters", "--also-agent", agent,
                                  "--also-agent-log", str(tmp_path / "agent0.log")],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + 30
        forked = []
        while not forked and time.monotonic() < deadline:
            forked = [pid for pid in processes_with("coordinator", "orphan") if pid != coord.pid]
            time.sleep(0.05)
        assert len(forked) == 1, "the coordinator did not fork its agent"
        time.sleep(1.0)  # the agent is up and waiting for the job to start
        assert alive(forked[0])
        coord.send_signal(signal.SIGKILL)
        coord.wait(10)
        deadline = time.monotonic() + 10
        while alive(forked[0]) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not alive(forked[0])
    finally:
        procs.stop_all()


def test_bad_agent_options_are_the_coordinators_one_line_error(tmp_path, capsys):
    features = tmp_path / "f.npz"
    ds = synthetic.sized(500)
    io.save_features(features, io.FeatureSet(ds.descriptors, ds.image_ids))
    base = ["coordinator", "--agents", "2", "--connect", "tcp/127.0.0.1:9", "--job", "bad", "--no-clusters"]
    good = f"--agents 2 --connect tcp/127.0.0.1:9 --job bad {features}"
    for options, message in ((f"--id 0 --no-such-option {good}", "unrecognized arguments: --no-such-option"),
                             (f"--id 0 'unbalanced {good}", "No closing quotation"),
                             (good, "required: --id")):
        assert main(base + ["--also-agent", options]) == 2, options
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--also-agent" in err[0] and message in err[0], err
        assert "Traceback" not in err[0]
    assert os.listdir(tmp_path) == ["f.npz"]

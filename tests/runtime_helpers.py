"""Shared by the runtime tests: the job data, process checks, a job held at a phase, dqm commands as processes."""
import os
import subprocess
import sys
import threading
import time

from dqm.synthetic import sift_like


def job_data():
    ds = sift_like(n_images=6, n_points=200, clutter_per_image=80, noise=0.3, seed=5)
    return ds.descriptors, ds.image_ids



def start_dqm(args, **kw):
    """``python -m dqm ARGS`` as a process in its own session (stdout and stderr piped, text)."""
    return subprocess.Popen([sys.executable, "-m", "dqm", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, **kw)


def alive(pid):
    """Whether the process runs (a zombie does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split()[2] != "Z"
    except OSError:
        return False


def start_held_job(X, ids, cfg, marker, env, **kw):
    """Start ``run_job`` in a thread and wait until an agent holds at its fault-hook phase (``marker`` written).

    Returns (thread, started processes, outcome): outcome gets "ok" (the report) or "error" (JobFailure).
    ``timeout_s``, ``ready_timeout_s``, ``max_lost``, ``recovery``: the job's runtime limits."""
    from dqm.runtime.launcher import JobFailure, run_job
    from dqm.runtime.limits import RuntimeLimits

    names = {"timeout_s": "job_timeout_s", "ready_timeout_s": "ready_timeout_s", "max_lost": "max_lost",
             "recovery": "recovery"}
    limits = RuntimeLimits(**{names[k]: kw.pop(k) for k in list(kw) if k in names})

    started, outcome = {}, {}

    def go():
        try:
            outcome["ok"] = run_job(X, ids, cfg, limits, env=env, on_started=started.update, **kw)
        except JobFailure as exc:
            outcome["error"] = exc

    th = threading.Thread(target=go)
    th.start()
    t0 = time.monotonic()
    while not marker.exists() and time.monotonic() - t0 < 60:
        time.sleep(0.02)
    assert marker.exists(), "the agent never reached the phase"
    return th, started, outcome


def wait_for_text(path, text, proc, timeout=60.0):
    """Wait until the log file ``path`` holds ``text``; fails if ``proc`` ends first or time runs out."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if text in path.read_text():
            return
        assert proc.poll() is None, path.read_text()
        time.sleep(0.05)
    raise AssertionError(f"{text!r} never appeared: {path.read_text()}")


def kill_all(procs):
    """Kill and reap the processes of ``procs`` that still run (None entries skipped)."""
    for p in procs:
        if p is not None and p.poll() is None:
            p.kill()
            p.wait()


def stop_once_ready(argv, log, ready, sig, settle=0.0, env=None, timeout=60.0):
    """``python -m dqm ARGV`` (stdout and stderr to the file ``log``), stopped with ``sig`` once its log holds
    ``ready`` and ``settle`` more seconds passed; returns the ended process and the seconds it took to leave."""
    with open(log, "w") as fh:
        p = subprocess.Popen([sys.executable, "-m", "dqm", *argv], stdout=fh, stderr=subprocess.STDOUT, env=env)
    try:
        wait_for_text(log, ready, p)
        time.sleep(settle)
        assert p.poll() is None, log.read_text()
        t = time.monotonic()
        p.send_signal(sig)
        p.wait(timeout=timeout)
        return p, time.monotonic() - t
    finally:
        kill_all([p])

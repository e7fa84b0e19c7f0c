"""Two jobs at the same time on ONE router, with different job ids (= key prefixes
dqm/<job>/...) but the same agent ids 0..M-1: neither sees the other's traffic and
each gives its own simulator's clusters."""
import numpy as np

from dqm import synthetic
from dqm.distributed import DQMConfig, simulate
from dqm.runtime.launcher import START_LIMITS, Processes, free_port, write_agent_files
from dqm.runtime.multihost import finish_job, start_job, start_router

M = 3


def test_two_concurrent_jobs_on_one_router_do_not_interfere(tmp_path):
    jobs = {
        "job-a": (synthetic.sift_like(n_images=6, n_points=200, seed=0), DQMConfig(agents=M, seed=1, job="job-a")),
        "job-b": (synthetic.sift_like(n_images=5, n_points=150, seed=7),
                  DQMConfig(agents=M, seed=4, partition="seeded", job="job-b")),
    }
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    procs = Processes()
    try:
        start_router(procs, [endpoint], tmp_path, ("127.0.0.1", port))
        running = {}
        for name, (ds, cfg) in jobs.items():  # start both before waiting for either
            wd = tmp_path / name
            wd.mkdir()
            files = write_agent_files(ds.descriptors, ds.image_ids, M, wd)
            running[name] = start_job(procs, cfg, files, wd, connect=lambda a: endpoint,
                                      limits=START_LIMITS.but(job_timeout_s=60))
        reports = {name: finish_job(job, 90) for name, job in running.items()}
    finally:
        procs.stop_all()
    for name, (ds, cfg) in jobs.items():
        rep = reports[name]
        assert rep["job"] == name
        assert rep["agent_exit_codes"] == [0] * M
        assert np.array_equal(np.asarray(rep["ids"]), np.arange(len(ds.descriptors)))
        assert np.array_equal(np.asarray(rep["labels"]), simulate(ds.descriptors, ds.image_ids, cfg).labels)
        # nothing of the other job arrived at all (not even to be rejected as "another job")
        assert not rep["rejected"], rep["rejected"]
    # the jobs really overlapped in time
    a, b = running["job-a"], running["job-b"]
    assert b.started < a.started + reports["job-a"]["wall_s"]

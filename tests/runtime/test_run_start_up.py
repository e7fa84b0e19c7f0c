"""`dqm run` before the job runs (issue 21): Ctrl-C and SIGTERM at any moment of the start-up end it
at once with its exit code and no traceback, leaving no process; agent counts beyond the host are
refused or warned about with a reason; large traffic tables are summarised."""
import os
import signal
import subprocess
import sys
import time

import pytest
from runtime_helpers import alive

from dqm import io, synthetic
from dqm.cli import main
from dqm.distributed.protocol import traffic_table
from dqm.runtime.launcher import MAX_AGENTS_PER_CORE, JobFailure, check_scale, overload_note
from dqm.runtime.lifeline import launched_by
from dqm.validation import InputError

pytest.importorskip("zenoh")


@pytest.fixture(scope="module")
def larger_job(tmp_path_factory):
    """40k generated features: the default scene's whole job (4k features) ends within 2.5 s on a fast
    machine, and then the signal no longer lands before the result; this one takes about 7 s there."""
    path = tmp_path_factory.mktemp("larger") / "f.npz"
    ds = synthetic.sized(40_000)
    io.save_features(path, io.FeatureSet(ds.descriptors, ds.image_ids))
    return path


@pytest.mark.parametrize("sig,delay,code", [(signal.SIGINT, 0.15, 130), (signal.SIGINT, 1.2, 130),
                                            (signal.SIGTERM, 2.5, 143)])
def test_a_signal_during_start_up_ends_the_job_at_once(tmp_path, larger_job, sig, delay, code):
    """12 agent processes take seconds to start on 2 cores: the signal lands while the command
    imports, while it forks the agents, or while they start; each time it must be obeyed."""
    p = subprocess.Popen([sys.executable, "-m", "dqm", "run", "--agents", "12", "--features", str(larger_job),
                          "--out", str(tmp_path / "c.npz")],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(delay)
    p.send_signal(sig)
    t0 = time.monotonic()
    out, err = p.communicate(timeout=60)
    assert p.returncode == code, (p.returncode, err[-2000:])
    assert time.monotonic() - t0 < 10
    assert "Traceback" not in err and "Exception ignored" not in err, err[-2000:]
    assert "interrupted" in err or "terminated" in err
    time.sleep(0.5)
    assert not [pid for pid in launched_by(p.pid) if alive(pid)]
    assert not (tmp_path / "c.npz").exists()


def test_agent_counts_beyond_the_host_are_refused_or_warned(tmp_path, capsys):
    assert main(["run", "--agents", "4000", "--out", str(tmp_path / "c.npz")]) == 2  # 400 GB of processes
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--agents 4000" in err[0] and "available" in err[0], err
    for bad in ("0", "-2"):
        with pytest.raises(SystemExit):
            main(["run", "--agents", bad])
        assert "--agents" in capsys.readouterr().err
    with pytest.warns(UserWarning, match="for 3 images: an agent starts with whole images, so 2 agents"):
        assert check_scale(5, 3) == 30.0
    cores = os.cpu_count() or 1
    with pytest.warns(UserWarning, match="on .* cores: the agent processes only share the cores"):
        timeout = check_scale(MAX_AGENTS_PER_CORE * cores, 10 ** 6)
    assert timeout > 30.0  # the ready timeout grows with the agents per core
    with pytest.raises(InputError, match=r"cannot keep their \d+ s liveliness leases"):
        check_scale(MAX_AGENTS_PER_CORE * cores + 1, 10 ** 6)


def test_agents_taken_for_lost_that_never_crashed_are_said_to_be_overloaded():
    failure = JobFailure("The distributed job failed: 147 agent processes were lost (6, 1, ...), more than the "
                         "limit of 75 (agent 114, phase routed).", 3, {"what": "147 agent processes were lost"})
    text = str(overload_note(failure, [3] * 100 + [0] * 50, 150))
    assert text.startswith(str(failure)) and "None of the 150 agent processes crashed" in text
    assert "Run fewer agents on this host" in text
    assert overload_note(failure, [3, -9, 0], 3) is failure  # one was killed: a real loss, nothing to add
    other = JobFailure("The distributed job failed: an agent refused the job", 4)
    assert overload_note(other, [0, 4], 2) is other


def test_large_traffic_tables_are_summarised():
    links = [{"src": f"agent{a}", "dst": f"agent{b}", "bytes": 1000 * a + b, "messages": 1}
             for a in range(40) for b in range(40) if a != b]
    rep = {"links": links, "kinds": {"ghost": {"bytes": 5, "messages": 1}},
           "total_bytes": sum(e["bytes"] for e in links)}
    text = traffic_table(rep, max_links=24)
    rows = [line for line in text.splitlines() if "->" in line]
    assert len(rows) == 24 and rows[0].startswith("| agent39 -> agent38 |")
    assert f"| {len(links) - 24} other links |" in text
    assert f"| total | {rep['total_bytes']} | {len(links)} |" in text
    assert len(traffic_table(rep).splitlines()) > len(links)


def test_statistics_of_a_large_job_are_accepted():
    """An agent reports bytes and messages per (destination, kind): 2,048 entries at 64 agents. A
    decoder limit of 1,024 map entries refused them, and the coordinator waited for them until its
    timeout (a 64-agent dqm run stalled)."""
    from dqm.distributed import messages

    values = {f"sent:{d}:{k}:{w}": 1.0 for d in range(64) for k in range(16) for w in ("bytes", "messages")}
    msg = messages.decode(messages.encode("stats", "job", 3, values=values), job="job", agents=64)
    assert msg["values"] == values

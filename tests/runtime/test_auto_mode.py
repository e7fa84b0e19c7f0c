"""--mode auto and --mode gather in the runtime: the link probes, the coordinator's pick and its report,
agents that run the mode it picked, and the gather path inside dqm run (labels identical to centralized)."""
import json
import subprocess
import sys
from itertools import count
from types import SimpleNamespace

import numpy as np
import pytest
from runtime_helpers import job_data

import dqm
from dqm import io
from dqm.distributed import DQMConfig, costmodel, simulate
from dqm.runtime import measure

MBIT = 1e6 / 8


@pytest.fixture(scope="module")
def data():
    return job_data()


# ---------------------------------------------------------------------- the probes, on a simulated link
class TokenBucketLink:
    """A link as tc tbf shapes it: ``rate`` bytes/s, a bucket of ``burst`` bytes that fills while idle, and
    ``latency`` seconds each way; the process answers at once. Time is simulated."""

    def __init__(self, rate: float, burst: float, latency: float = 2e-4):
        self.rate, self.burst, self.latency = rate, burst, latency
        self.now = 0.0
        self.tokens, self.t_tokens, self.free = burst, 0.0, 0.0
        self.arrivals = {}

    def _deliver(self, nbytes: int, t: float) -> float:
        t = max(t, self.free)
        self.tokens = min(self.burst, self.tokens + self.rate * (t - self.t_tokens))
        if nbytes <= self.tokens:
            self.tokens -= nbytes
            done = t
        else:
            done = t + (nbytes - self.tokens) / self.rate
            self.tokens = 0.0
        self.t_tokens = self.free = done
        return done

    def send_pair(self, process, a, b, nbytes):
        for token in (a, b):
            self.arrivals[token] = self._deliver(nbytes, self.now + self.latency) + 2 * self.latency

    def await_reply(self, token, timeout_s):
        t = self.arrivals.pop(token)
        self.now = max(self.now, t)
        return t

    def clock(self):
        return self.now


def probe_eight(rate: float, burst: float, enough=None) -> list:
    """The coordinator's probes of 8 processes behind one token-bucket link, one after the other, each starting
    at the size the one before needed."""
    link, tokens = TokenBucketLink(rate, burst), count(1)
    start, out = measure.START_PROBE_BYTES, []
    for p in range(8):
        out.append(measure.measure_link(p, link.send_pair, link.await_reply, tokens, link.clock, start, enough))
        start = measure.next_start_bytes(out[-1])
    return out


@pytest.mark.parametrize("mbit", [10, 100, 1000, 20000])
def test_probe_pairs_measure_the_sustained_rate_past_the_burst(mbit):
    rate = mbit * MBIT
    burst = max(96 * 1024, rate / 250)  # as EmulatedHosts shapes its links
    measured = probe_eight(rate, burst)
    for p, r in enumerate(measured):
        if mbit <= 1000:  # a link the largest probe can fill for long enough
            assert r.bytes_s == pytest.approx(rate, rel=0.05), (p, r)
        else:  # faster than 8 MiB / MIN_SPREAD_S: at least that
            assert r.bytes_s > 0.5 * rate and r.probe_bytes == measure.MAX_PROBE_BYTES
    total = sum(r.seconds for r in measured)
    assert total < 2.5, total  # a second or two for 8 processes, even at 10 Mbit/s


@pytest.mark.parametrize("mbit", [10, 100, 1000])
def test_a_probe_pair_past_the_burst_settles_a_link_known_fast_enough(mbit):
    """With enough_bytes_s (20 Mbit/s here), a link whose first pair's lower bound (a probe's size over the time to
    the second answer) reaches it is left at that bound after one pair; a slower one is measured as before."""
    rate = mbit * MBIT
    burst = max(96 * 1024, rate / 250)
    settled, full = probe_eight(rate, burst, 20 * MBIT), probe_eight(rate, burst)
    for r in settled:
        if mbit > 20:
            assert r.at_least and r.rounds == 1 and r.bytes_s >= 20 * MBIT, r
            if burst <= r.probe_bytes:  # a lower bound (a larger burst carries a whole pair at once)
                assert r.bytes_s <= rate
        else:
            assert not r.at_least and r.bytes_s == pytest.approx(rate, rel=0.05)
    # asked for less than the link has, the slow link too ends after one pair, at a bound under its rate
    link = TokenBucketLink(rate, burst)
    low = measure.measure_link(0, link.send_pair, link.await_reply, count(1), link.clock, measure.START_PROBE_BYTES,
                               0.2 * min(rate, 20 * MBIT))
    assert low.at_least and low.rounds == 1 and (low.bytes_s <= rate or burst > low.probe_bytes)
    if mbit > 20:
        assert sum(r.seconds for r in settled) < 0.5 * sum(r.seconds for r in full)


def test_cgroup_quota_is_read_along_the_path(tmp_path):
    v1 = tmp_path / "cpu"
    (v1 / "a" / "b").mkdir(parents=True)
    for d, quota in ((v1, -1), (v1 / "a", 150000), (v1 / "a" / "b", 300000)):
        (d / "cpu.cfs_quota_us").write_text(f"{quota}\n")
        (d / "cpu.cfs_period_us").write_text("100000\n")
    cg = tmp_path / "cgroup"
    cg.write_text("4:memory:/x\n1:cpu:/a/b\n")
    assert measure._cgroup_quota(tmp_path, cg) == pytest.approx(1.5)  # the parent's is the tighter
    (tmp_path / "u" / "s").mkdir(parents=True)
    (tmp_path / "u" / "s" / "cpu.max").write_text("50000 100000\n")
    cg.write_text("0::/s\n")
    assert measure._cgroup_quota(tmp_path / "u", cg) == pytest.approx(0.5)
    cg.write_text("1:cpu:/nowhere\n")
    assert measure._cgroup_quota(tmp_path / "empty", cg) is None
    assert 0 < measure.host_cores() <= 4096


# ---------------------------------------------------------------------- an agent started with mode auto
def test_an_auto_agent_takes_the_mode_the_coordinator_names(data):
    from dqm.distributed.hosting import ProcessHost
    from dqm.distributed.sources import agent_features

    X, ids = data
    own = agent_features([io.FeatureSet(X[:10], ids[:10])], 0)
    bus = SimpleNamespace(dim=None)
    auto = ProcessHost(0, DQMConfig(agents=2, mode="auto", job="j"), bus, own, load=None)
    for mode in ("auto", "gather", "lean", "balanced"):
        assert auto.job_config(DQMConfig(agents=2, mode=mode, job="j").params_text()).mode == mode
    # a mode auto never picks stays a difference the parameter check names
    assert auto.job_config(DQMConfig(agents=2, mode="paper").params_text()).mode == "auto"
    fixed = ProcessHost(0, DQMConfig(agents=2, mode="balanced", job="j"), bus, own, load=None)
    assert fixed.job_config(DQMConfig(agents=2, mode="auto").params_text()).mode == "balanced"


# ---------------------------------------------------------------------- jobs
def test_dqm_run_mode_auto_picks_records_and_matches_the_mode_it_ran(tmp_path):
    from dqm.synthetic import sift_like

    ds = sift_like(n_images=6, n_points=700, clutter_per_image=80, noise=0.3, seed=5)
    X, ids = ds.descriptors, ds.image_ids
    job = costmodel.JobShape(n=len(X), agents=3, dim=128)
    # on one host gather wins at every link rate, whatever its cores and pair rate (one process matches on every
    # core, where the agents would share them, and moves the fewest bytes), so dqm run's auto never times them
    for host in (1.0, 2.0, 16.0):
        for speed in (0.3, 1.0, 10.0):
            found = costmodel.rate_free_choice(job, lambda r, host=host, speed=speed: costmodel.Hosts.of(
                [r] * 3, host / 3, gather_cores=host, kernel_cpu_s=speed * costmodel.FITTED.kernel_cpu_s))
            assert found is not None and found[:2] == ("gather", 1.0), (host, speed, found)
    # between balanced and lean it may turn on the rate: the coordinator's decision is the cost model's on the
    # inputs its report records (this host's cores and measured pair rate), with probes or without
    features = tmp_path / "f.npz"
    io.save_features(features, io.FeatureSet(X, ids))
    report, out = tmp_path / "r.json", tmp_path / "c.npz"
    p = subprocess.run([sys.executable, "-m", "dqm", "run", "--agents", "3", "--mode", "auto", "--auto-modes",
                        "balanced,lean", "--features", str(features), "--job", "auto-cli", "--report", str(report),
                        "--out", str(out)], capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stderr[-2000:]
    rep = json.loads(report.read_text())
    auto = rep["auto"]
    assert auto["picked"] == rep["mode"] and auto["picked"] in ("balanced", "lean")
    assert auto["features"] == len(X) and auto["kernel_cpu_s"] > 0 and auto["reason"].startswith(auto["picked"])

    def hosts(rates):
        return costmodel.Hosts.of(rates, auto["cores_per_host"], gather_cores=auto["gather_cores"],
                                  kernel_cpu_s=auto["kernel_cpu_s"])

    clear = costmodel.rate_free_choice(job, lambda r: hosts([r] * 3), modes=("balanced", "lean"))
    line = next(ln for ln in p.stdout.splitlines() if ln.startswith("--mode auto picked"))
    assert auto["reason"] in line
    if auto["rates_bytes_s"]:  # the links were timed: the model could not pick without them
        assert clear is None
        assert set(auto["rates_bytes_s"]) == {"0", "1", "2"} and all(r > 0 for r in auto["rates_bytes_s"].values())
        assert set(auto["predicted_s"]) == {"balanced", "lean"} and "Mbit/s per process" in line
        assert auto["probe_bytes"] > 0 and "probe" not in rep["kinds"]  # probes are not the job's traffic
        rates = [auto["rates_bytes_s"][str(q)] for q in range(3)]
        settled = costmodel.settled_above(job, lambda r: hosts([r] * 3), modes=("balanced", "lean"))
        enough = None if settled is None else settled[0] * costmodel.SETTLED_MARGIN
        # on loopback every link is far faster than any settled rate: shown so by one pair each (a lower bound)
        assert auto["rates_at_least"] == ([] if settled is None else ["0", "1", "2"])
        if settled is not None:
            assert all(r >= enough for r in rates) and auto["picked"] == settled[1]
            assert all(len(pairs) == 1 for pairs in auto["probe_pairs"].values())
        else:
            assert costmodel.choose(job, hosts(rates), modes=("balanced", "lean")).mode == auto["picked"]
    else:
        assert clear is not None and clear[0] == auto["picked"] and auto["probe_bytes"] == 0
        assert "without timing the links" in line
    assert rep["epochs"] == 1 and rep["agent_exit_codes"] == [0, 0, 0]
    assert f"({auto['picked']} mode" in p.stdout
    labels = np.asarray(rep["labels"])
    np.testing.assert_array_equal(np.asarray(rep["ids"]), np.arange(len(X)))
    np.testing.assert_array_equal(labels, simulate(X, ids, DQMConfig(agents=3, mode=rep["mode"])).labels)
    np.testing.assert_array_equal(io.load_clusters(out)["labels"], labels)


def test_auto_runs_the_mode_it_picked_as_that_mode_runs(data):
    from dqm.runtime.launcher import run_job
    from dqm.runtime.limits import RuntimeLimits

    X, ids = data
    cfg = DQMConfig(agents=2, seed=3, mode="auto", auto_modes="balanced", job="auto-balanced")
    rep = run_job(X, ids, cfg, RuntimeLimits(job_timeout_s=120))
    assert rep["mode"] == rep["auto"]["picked"] == "balanced"
    # one mode to pick from: the links cannot change the answer, so nothing was timed
    assert rep["auto"]["rates_bytes_s"] == {} and rep["auto"]["probe_s"] == 0 and rep["auto"]["probe_bytes"] == 0
    assert "without timing the links" in rep["auto"]["reason"]
    # the coordinator timed this host's all-pairs kernel, and the pick says how it scaled the pair work
    assert rep["auto"]["kernel_cpu_s"] > 0 and "x the fit's CPU time" in rep["auto"]["reason"]
    sim = simulate(X, ids, cfg.but(mode="balanced"))
    np.testing.assert_array_equal(np.asarray(rep["labels"]), sim.labels)
    # the same messages as the balanced job, one start included (its parameters say mode auto, and go
    # names the mode: a few bytes apart)
    skip = ("stats", "progress", "go", "start")
    assert {k: (v["bytes"], v["messages"]) for k, v in rep["kinds"].items() if k not in skip} == \
        {k: v for k, v in sim.traffic.per_kind().items() if k not in skip}
    for kind in ("go", "start"):
        assert rep["kinds"][kind]["messages"] == sim.traffic.per_kind()[kind][1]
    assert rep["epochs"] == 1


def test_auto_skips_the_probes_only_where_the_links_cannot_change_the_answer_much():
    """The cost model at every rate of CLEAR_RATES_BYTES_S: graf's size on 8 hosts of 0.25 cores is gather
    (within 1% of balanced at 1 Mbit/s, the fastest at every other rate) on a machine as fast as the fit's at
    the pairs, balanced on one 3x slower; 100k features on the same hosts turn on the rate (below about 3.3
    Mbit/s balanced's bulk traffic would starve the keep-alives), so the links are timed; a small job is
    gather at every rate."""
    from dqm.distributed.coordination import CoordinatorCore

    def core_ready(m: int, n: int) -> CoordinatorCore:
        core = CoordinatorCore(DQMConfig(agents=m, mode="auto", job="j"))
        core.begin()
        for p in range(m):
            core.handle({"kind": "ready", "src": p, "epoch": 0, "dim": 128, "dtype": "|u1",
                         "hosted": np.array([p]), "features": n // m})
        assert core.phase == "probe"
        return core

    fit = costmodel.FITTED.kernel_cpu_s
    for speed, mode, how in ((1.0, "gather", "within 0.6% of the fastest"), (3.0, "balanced", "the fastest")):
        clear = core_ready(8, 21691)
        assert clear.decide_unmeasured(0.25, 0.25, speed * fit)
        assert clear.phase == "running" and clear.cfg.mode == mode and clear.auto["rates_bytes_s"] == {}
        assert clear.auto["reason"].startswith(f"{mode} without timing the links: {how} at every link rate")
        assert f"pair work at {speed:.2f}x the fit's CPU time" in clear.auto["reason"]
        assert set(clear.auto["predicted_s"]) == {mode} and clear.auto["kernel_cpu_s"] == speed * fit
        assert [fields for _, kind, fields in clear.take_outbox() if kind == "go"] == [{"mode": mode}] * 8
    unclear = core_ready(8, 100186)
    assert not unclear.decide_unmeasured(0.25, 0.25, fit) and unclear.phase == "probe" and unclear.auto is None
    picks = {costmodel.choose(costmodel.JobShape(n=100186, agents=8, dim=128),
                              costmodel.Hosts.of([r] * 8, 0.25, gather_cores=0.25, kernel_cpu_s=fit)).mode
             for r in costmodel.CLEAR_RATES_BYTES_S}
    assert picks == {"gather", "balanced"}
    # a small job: agent 0 gathers the others' features (they cross one link, its own none) at every rate
    small = core_ready(3, 1321)
    assert small.decide_unmeasured(0.66, 2.0) and small.cfg.mode == "gather"
    assert clear.settled is None and small.settled is None  # nothing to settle: no probes at all

    # 100k: settled above some rate; links that one pair shows at least SETTLED_MARGIN x that fast need no finer
    # timing, and the pick is the settled mode
    floor, mode = unclear.settled
    assert mode == "balanced" and unclear.enough_rate == floor * costmodel.SETTLED_MARGIN
    fast = {p: unclear.enough_rate * (1 + p) for p in range(8)}
    unclear.decide(fast, 0.25, 0.25, 0.3, kernel_cpu_s=fit, at_least=range(8))
    assert unclear.cfg.mode == "balanced" and unclear.auto["rates_at_least"] == [str(p) for p in range(8)]
    assert unclear.auto["reason"].startswith(f"balanced: every link measured at least "
                                             f"{costmodel.mbit_text(unclear.enough_rate)} Mbit/s")
    # one link below it (measured in full): the model's pick at the rates read, as before
    slow = core_ready(8, 100186)
    assert not slow.decide_unmeasured(0.25, 0.25, fit)
    rates = {**fast, 3: 1 * MBIT}
    slow.decide(rates, 0.25, 0.25, 0.3, kernel_cpu_s=fit, at_least=[p for p in range(8) if p != 3])
    want = costmodel.choose(slow.job_shape(), costmodel.Hosts.of([rates[p] for p in range(8)], 0.25, gather_cores=0.25,
                                                                  kernel_cpu_s=fit))
    assert slow.cfg.mode == want.mode and slow.auto["reason"] == want.reason


def test_auto_mode_predicts_the_engine_the_job_runs():
    """--mode auto with --engine fast (or auto at 100k features) predicts the fast engine's modes: the pick,
    its predicted seconds and the reason are the cost model's for that engine, the report names it, and go
    names the engine only where it was auto."""
    from dqm.distributed.coordination import CoordinatorCore

    fit = costmodel.FITTED.kernel_cpu_s
    rates = {p: 100 * MBIT for p in range(8)}
    seconds = {}
    for engine, n, runs in (("fast", 100186, "fast"), ("auto", 100186, "fast"), ("auto", 21691, "exact"),
                            ("exact", 100186, "exact")):
        core = CoordinatorCore(DQMConfig(agents=8, mode="auto", engine=engine, job="j"))
        core.begin()
        for p in range(8):
            core.handle({"kind": "ready", "src": p, "epoch": 0, "dim": 128, "dtype": "|u1",
                         "hosted": np.array([p]), "features": n // 8})
        job = core.job_shape()
        assert job.engine == runs and job.copies_per_feature == core.cfg.copies_per_feature
        if not core.decide_unmeasured(0.25, 0.25, fit):
            core.decide(rates, 0.25, 0.25, 0.3, kernel_cpu_s=fit)
        want = costmodel.choose(job, costmodel.Hosts.of([100 * MBIT] * 8, 0.25, gather_cores=0.25,
                                                        kernel_cpu_s=fit))
        assert core.cfg.mode == want.mode and core.cfg.engine == runs and core.auto["engine"] == runs
        assert f"{runs} engine" in core.auto["reason"]
        go = [fields for _, kind, fields in core.take_outbox() if kind == "go"]
        assert go == [{"mode": want.mode, **({"engine": runs} if engine == "auto" else {})}] * 8
        seconds[engine, n] = want.predictions[want.mode].seconds
    # at 100k the fast engine's pick is predicted faster than the exact engine's
    assert seconds["fast", 100186] == seconds["auto", 100186] < seconds["exact", 100186]


@pytest.mark.parametrize("kernel", ["quadratic", "gaussian"])
def test_gather_inside_dqm_run_equals_centralized(data, tmp_path, kernel):
    from dqm.runtime.launcher import run_job
    from dqm.runtime.limits import RuntimeLimits

    X, ids = data
    cfg = DQMConfig(agents=3, seed=2, mode="gather", kernel=kernel, job=f"gather-{kernel}")
    out = tmp_path / "c.npz"
    rep = run_job(X, ids, cfg, RuntimeLimits(job_timeout_s=120),
                  clusters=str(out) if kernel == "quadratic" else None)
    assert rep["mode"] == "gather" and "auto" not in rep and rep["agent_exit_codes"] == [0, 0, 0]
    labels = np.asarray(rep["labels"])
    np.testing.assert_array_equal(labels, dqm.quickmatch(X, ids, params=cfg.params).labels)
    # the report a distributed job writes: ids, labels, bytes per link and kind, times, per-agent stats
    assert rep["features"] == len(X) and rep["clusters"] == labels.max() + 1
    # agent 0 gathers: the other two send it their features (its own cross no link), it sends the labels
    assert rep["kinds"]["gather"]["messages"] >= 2 and rep["kinds"]["result"]["messages"] == 1
    assert rep["total_bytes"] > X.size * 2 / 3 * 0.5
    links = {(e["src"], e["dst"]) for e in rep["links"]}
    assert {("agent1", "agent0"), ("agent2", "agent0")} <= links  # (agent 0 -> 1, 2: its acknowledgements)
    assert {e["src"] for e in rep["links"] if e["dst"] == "coordinator"} == {"agent0", "agent1", "agent2"}
    assert set(rep["per_agent"]) == {"0", "1", "2"} and rep["time_run_s"] > 0 and rep["match_s"] > 0
    if kernel == "quadratic":
        np.testing.assert_array_equal(labels, simulate(X, ids, cfg.but(mode="balanced")).labels)
        np.testing.assert_array_equal(io.load_clusters(out)["labels"], labels)

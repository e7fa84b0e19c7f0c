"""The simulator's fault plan: lost acks, duplicates, delays and lost processes replayed without zenoh,
deterministically, through the same delivery layer, coordinator core and process host as the runtime."""
import numpy as np
import pytest

from dqm import synthetic
from dqm.distributed import DQMConfig, protocol, simulate
from dqm.distributed.driver import states_for
from dqm.distributed.network import Delay, Drop, Duplicate, FaultPlan, LoseProcess
from dqm.validation import InputError


@pytest.fixture(scope="module")
def data():
    ds = synthetic.sized(2000, seed=4)
    return ds.descriptors, ds.image_ids


@pytest.fixture(scope="module")
def clean(data):
    X, ids = data
    return {mode: simulate(X, ids, DQMConfig(agents=3, seed=2, mode=mode)) for mode in ("balanced", "lean", "paper")}


def _run(data, mode, faults, **kw):
    X, ids = data
    plan = FaultPlan(faults)
    return simulate(X, ids, DQMConfig(agents=3, seed=2, mode=mode), faults=plan, **kw), plan


@pytest.mark.parametrize("mode,kind", [("balanced", "ghost"), ("balanced", "features"), ("lean", "features")])
def test_a_lost_ack_is_resent_and_the_copy_dropped(data, clean, mode, kind):
    r, plan = _run(data, mode, [Drop("ack", src=2, dst=0, nth=1), Drop(kind, src=1, nth=1)])
    assert len(plan.struck) == 2  # both faults happened
    np.testing.assert_array_equal(r.labels, clean[mode].labels)
    resends, dups = r.traffic.counters()[2], r.traffic.counters()[1]
    assert resends == 2  # the message whose ack was lost, and the dropped one
    assert dups == 1  # the resent copy of the message that had arrived: acknowledged again, used once
    assert r.epochs == 1 and r.lost == []
    # the resends and their acks are extra bytes; nothing else changes
    assert r.traffic.total() > clean[mode].traffic.total()


@pytest.mark.parametrize("kind", ["features", "component", "start"])
def test_a_duplicated_message_is_used_once(data, clean, kind):
    r, plan = _run(data, "balanced", [Duplicate(kind, nth=1)])
    assert len(plan.struck) == 1
    np.testing.assert_array_equal(r.labels, clean["balanced"].labels)
    assert r.traffic.counters()[1] == 1
    # the network made the copy, not the sender: only an acknowledged kind's second ack is extra traffic
    extra = r.traffic.total() - clean["balanced"].traffic.total()
    assert extra == r.traffic.per_kind()["ack"][0] - clean["balanced"].traffic.per_kind()["ack"][0]
    assert (extra > 0) == (kind in protocol.ACKED)


@pytest.mark.parametrize("seconds,resent", [(1.0, 0), (30.0, 1)])
def test_a_delayed_part_arrives_late_or_is_overtaken_by_its_resend(data, clean, seconds, resent):
    """Delayed less than the first resend timeout (2 s): it arrives after the messages sent after it, and
    nothing is resent. Delayed longer: the resent copy arrives first; the late one is a duplicate."""
    r, plan = _run(data, "balanced", [Delay("density", src=0, dst=1, nth=1, seconds=seconds)])
    assert len(plan.struck) == 1
    np.testing.assert_array_equal(r.labels, clean["balanced"].labels)
    assert r.traffic.counters()[2] == resent and r.traffic.counters()[1] == resent


def test_only_resent_kinds_may_be_dropped():
    with pytest.raises(InputError, match="only acknowledged kinds"):
        FaultPlan([Drop("result")])
    with pytest.raises(InputError, match="nth must be at least 1"):
        FaultPlan([Duplicate("features", nth=0)])


def _states(mode):
    # the set-up's fill and weights rounds happen only when the job needs them (these jobs: weights only
    # in balanced mode, which weighs its cells; fill never)
    skip = {"wait_fill"} | ({"wait_weights"} if mode != "balanced" else set())
    return [(mode, s) for s in states_for(mode) if s not in skip]


# paper passes lean's states with the same cascade core (its own takeover: the test below)
@pytest.mark.parametrize("mode,state", _states("balanced") + _states("lean"))
def test_a_process_lost_in_any_state_gives_the_fault_free_labels(data, clean, mode, state):
    r, _ = _run(data, mode, [LoseProcess(1, state)])
    np.testing.assert_array_equal(r.labels, clean[mode].labels)
    if state == "wait_finish":  # it had delivered its results and statistics: nothing to redo
        assert r.lost == [] and r.epochs == 1
    elif state == "wait_start":  # before go nothing was computed: the next epoch starts everything
        assert r.lost == [{"process": 1, "phase": "start", "epoch": 0, "recovery": "restart"}] and r.epochs == 2
    else:  # the survivors keep their work; agent 1 runs again at process 2, fed again by the others
        assert [(x["process"], x["recovery"]) for x in r.lost] == [(1, "takeover")] and r.epochs == 1


@pytest.mark.parametrize("mode,state", [("balanced", "wait_routed"), ("balanced", "wait_density"),
                                        ("lean", "wait_handdown"), ("paper", "wait_acks")])
def test_a_takeover_costs_less_than_a_restart_and_gives_the_same_labels(data, clean, mode, state):
    took, _ = _run(data, mode, [LoseProcess(1, state)])
    again, _ = _run(data, mode, [LoseProcess(1, state)], recovery="restart")
    np.testing.assert_array_equal(took.labels, clean[mode].labels)
    np.testing.assert_array_equal(again.labels, clean[mode].labels)
    assert again.epochs == 2 and again.lost[0]["recovery"] == "restart"
    base = clean[mode].traffic.total()
    # a restart sends the abandoned epoch's messages again; a takeover only what the lost agent had
    # received and what it sends again (dropped as duplicates where they had arrived)
    assert base < took.traffic.total() < again.traffic.total()


@pytest.mark.parametrize("state", ["wait_seeds", "wait_ghost", "wait_acks"])
def test_the_leader_lost_and_then_its_heir(data, clean, state):
    """Process 0 leads the set-up; lost, its agent goes to process 1, which is lost later while it hosts
    both: agents 0 and 1 go to process 2, the last one, which runs them again from their start (when
    process 0 is lost late, process 1 goes first and both agents still end at process 2)."""
    r, _ = _run(data, "balanced", [LoseProcess(0, state), LoseProcess(1, "wait_component")], max_lost=2)
    np.testing.assert_array_equal(r.labels, clean["balanced"].labels)
    # (lost at wait_acks, late, process 0 goes after process 1)
    assert sorted((x["process"], x["phase"]) for x in r.lost) == [(0, state[5:]), (1, "component")]
    assert r.epochs == 1


def test_more_losses_than_allowed_fail_the_job(data):
    from dqm.distributed.coordination import JobFailed

    with pytest.raises(JobFailed, match="more than the limit of 0"):
        _run(data, "balanced", [LoseProcess(1, "wait_ghost")], max_lost=0)


@pytest.mark.parametrize("first,then", [("wait_acks", "wait_finish"), ("wait_component", "wait_finish"),
                                        ("wait_finish", "wait_ghost")])
def test_a_finished_process_lost_around_a_takeover(data, clean, first, then):
    """Process 2 is lost, then process 1 (or the other way round), one of them after delivering everything.
    A finished agent's process that goes while another agent runs again takes its messages with it: the
    finished agent runs again too. One that goes with no takeover under way is harmless: nobody waits for
    its acks any more (``gone``), and a later takeover runs it again if needed."""
    r, plan = _run(data, "balanced", [LoseProcess(2, first), LoseProcess(1, then)], max_lost=2)
    np.testing.assert_array_equal(r.labels, clean["balanced"].labels)
    assert r.epochs == 1 and {x["recovery"] for x in r.lost} <= {"takeover"}


def test_the_first_resend_waits_for_the_bytes_ahead_at_the_floor_rate():
    """A part queued behind megabytes on a thin link is not resent after the plain 2-s timeout: it waits at
    least as long as the bytes put before it (itself included) take at 1 Mbit/s."""
    from dqm.distributed.delivery import FLOOR_BYTES_S, Delivery
    from dqm.distributed.ledger import Meter

    d = Delivery("j", Meter())
    part = b"x" * 1_000_000
    assert d.sending(0, 1, "ghost", part, 0, now=0.0) and d.sending(0, 2, "ghost", part, 0, now=0.0)
    assert d.due(2.5) == []  # the adaptive timeout alone (2 s) would have resent both
    first, second = len(part) / FLOOR_BYTES_S, 2 * len(part) / FLOOR_BYTES_S
    assert [r.dst for r in d.due(first + 0.01)] == [1]
    assert sorted(r.dst for r in d.due(second + 0.02)) == [1, 2]
    assert d.meter.counters()[2] == 3  # each resend counted
    # a takeover's replay puts everything again at once: the same floor (agent 2's part behind agent 1's)
    t = 100.0
    d.receive({"kind": "ack", "src": 1, "dst": 0, "seq": 0, "epoch": 0}, 0, t)
    d.receive({"kind": "ack", "src": 2, "dst": 0, "seq": 0, "epoch": 0}, 0, t)
    assert d.unacknowledged() == 0
    assert [r.dst for r in d.replay([1, 2], now=t)] == [1, 2]
    assert d.due(t + 2.5) == []
    assert [r.dst for r in d.due(t + first + 0.01)] == [1]
    assert sorted(r.dst for r in d.due(t + second + 0.02)) == [1, 2]


def test_next_resend_time_follows_every_change_of_what_is_pending():
    """next_due (kept between changes, as the simulator asks after every message) equals the earliest due time
    computed afresh after sends, returned puts, acks (which also change a link's round trip), resends, a
    finished agent and a replay."""
    from dqm.distributed.delivery import Delivery
    from dqm.distributed.ledger import Meter

    d = Delivery("j", Meter())

    def fresh():
        times = [p.sent_at + d._timeout(k[1], p) for k, p in d._pending.items()]
        return min(times) if times else None

    rng = np.random.default_rng(0)
    now, seq, checked = 0.0, 0, 0
    for step in range(400):
        now += float(rng.exponential(0.3))
        op = rng.integers(0, 6)
        pending = list(d._pending)
        if op <= 1:
            dst = int(rng.integers(1, 4))
            if d.sending(0, dst, "ghost", b"x" * int(rng.integers(1, 50_000)), seq, now):
                assert d.next_due() == fresh()  # asked while the put is under way
                d.put_returned(0, dst, seq, now + float(rng.random()))
            seq += 1
        elif op == 2 and pending:
            src, dst, s = pending[int(rng.integers(len(pending)))]
            d.receive({"kind": "ack", "src": dst, "dst": src, "seq": s, "epoch": 0}, src, now)
        elif op == 3:
            d.due(now)
        elif op == 4 and step % 50 == 0:
            d.forget([int(rng.integers(1, 4))])
        elif op == 5 and step % 40 == 0:
            d.replay([int(rng.integers(1, 4))], now)
        assert d.next_due() == fresh(), step
        checked += d.next_due() is not None
    assert checked > 100 and d.meter.counters()[2] > 0  # resends happened

"""The one agent driver (sans I/O) and the one traffic ledger, driven by hand over the in-memory bus."""
import numpy as np
import pytest

from dqm import synthetic
from dqm.distributed import DQMConfig, simulate
from dqm.distributed.driver import STATES, AgentDriver, states_for
from dqm.distributed.ledger import COORDINATOR, TrafficLedger
from dqm.distributed.network import MemoryNetwork
from dqm.distributed.sources import agent_features, split_features
from dqm.io import FeatureSet


def _drive(X, ids, cfg):
    """Run a job with bare drivers on the memory network (no coordinator, no process host): deliver,
    settle, repeat. Returns drivers, network, visited states."""
    held = [agent_features([p], a) for a, p in enumerate(split_features(FeatureSet(X, ids), cfg.agents))]
    net = MemoryNetwork(cfg.job, cfg.agents, X.shape[1])
    seen = {a: [] for a in range(cfg.agents)}
    drivers = [AgentDriver(a, cfg, net.endpoint(a), h.ids, h.image_ids, h.descriptors,
                           on_state=lambda agent, state: seen[agent].append(state)) for a, h in enumerate(held)]
    for d in drivers:
        d.begin(cfg.seed)
    results = {}
    for _ in range(100_000):
        for d in drivers:
            d.settle()
        item = net.next()
        if item is None:
            break
        p, dst, msg = item
        if not net.endpoint(p).accept(dst, msg):
            continue
        if dst == COORDINATOR:
            if msg["kind"] == "result":
                results[msg["src"]] = msg
        else:
            drivers[dst].handle(msg)
    return drivers, net, seen, results


@pytest.mark.parametrize("mode", ["balanced", "lean"])
def test_bare_drivers_reproduce_the_simulator(mode):
    ds = synthetic.sized(3000, seed=4)
    cfg = DQMConfig(agents=3, seed=2, mode=mode, job="drv").validated(len(ds.descriptors))
    drivers, bus, seen, results = _drive(ds.descriptors, ds.image_ids, cfg)
    sim = simulate(ds.descriptors, ds.image_ids, cfg)
    order = states_for(mode)
    for a, states in seen.items():
        assert states[-1] == "wait_finish" and drivers[a].state == "wait_finish"
        idx = [order.index(s) for s in states]
        assert idx == sorted(idx)  # explicit states, visited in their declared order
        assert set(states) <= set(STATES)
    # the algorithm's traffic equals the simulator's (which also plays start/ready/go/finish)
    control = ("start", "ready", "go", "finish")
    ours = {k: v for k, v in bus.meter.per_kind().items() if k not in control}
    assert ours == {k: v for k, v in sim.traffic.per_kind().items() if k not in control}
    holder = np.full(len(ds.descriptors), -1)
    for a, msg in results.items():
        holder[msg["ids"]] = a
    np.testing.assert_array_equal(holder, sim.holder)


def test_ledger_stats_fields_round_trip():
    led = TrafficLedger()
    led.add(0, 1, "features", 1000)
    led.add(0, 1, "features", 500)
    led.add(0, -1, "result", 77)
    led.add(1, 0, "ack", 40)
    back = TrafficLedger()
    back.add_stats(0, {**led.as_stats(src=0), "cpu_s": 1.5})
    assert back.entries() == {k: v for k, v in led.entries().items() if k[0] == 0}
    assert back.entries()[(0, 1, "features")] == (1500, 2)
    assert TrafficLedger.strip_stats({**led.as_stats(), "cpu_s": 1.5}) == {"cpu_s": 1.5}
    rep = led.report()
    assert rep["total_bytes"] == 1617 and rep["kinds"]["features"] == {"bytes": 1500, "messages": 2}
    assert {(e["src"], e["dst"]) for e in rep["links"]} == {("agent0", "agent1"), ("agent0", "coordinator"),
                                                           ("agent1", "agent0")}


def test_driver_refuses_a_state_outside_its_mode():
    ds = synthetic.sized(400, seed=1)
    cfg = DQMConfig(agents=2, mode="lean").validated(len(ds.descriptors))
    net = MemoryNetwork(cfg.job, 2, ds.descriptors.shape[1])
    d = AgentDriver(0, cfg, net.endpoint(0), np.arange(10), ds.image_ids[:10], ds.descriptors[:10])
    with pytest.raises(AssertionError, match="no state 'wait_ghost' in a lean job"):
        d._enter("wait_ghost")

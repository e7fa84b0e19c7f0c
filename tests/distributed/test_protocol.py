"""The resend policy of acknowledged messages (dqm.distributed.protocol.Retransmit)."""
from dqm.distributed.protocol import Retransmit


def test_retransmit_backs_off_and_follows_the_measured_round_trip():
    """The resend policy (dqm.distributed.protocol.Retransmit): never below the base, doubling per resend up
    to the cap, and tracking a link's acknowledgement round trips (first tries only)."""
    r = Retransmit(base_s=2.0, max_s=60.0, factor=3.0)
    assert [r.timeout(1, k) for k in (1, 2, 3, 4, 6, 10)] == [2.0, 4.0, 8.0, 16.0, 60.0, 60.0]
    r.acknowledged(1, 0.05, tries=1)  # a fast link keeps the base
    assert r.timeout(1, 1) == 2.0
    for _ in range(40):  # a saturated thin link: acks take 3 s
        r.acknowledged(2, 3.0, tries=1)
    assert 8.9 < r.timeout(2, 1) <= 9.0 and r.timeout(2, 2) == 2 * r.timeout(2, 1)
    before = r.timeout(2, 1)
    r.acknowledged(2, 100.0, tries=2)  # an ack of a resent message is not matched to one send
    r.acknowledged(2, float("nan"), tries=1)
    assert r.timeout(2, 1) == before and r.timeout(3, 1) == 2.0  # other links keep their own

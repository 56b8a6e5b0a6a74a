"""The whole-run line of ``rlbridge bench load``, from a real server's ``Stats`` reply.

"never reached the server" is the sum of the sequence gaps the server's publish channels
counted. Subscribe channels report ``lost`` as -1 (the client measures that hop); summed in,
they made the figure one smaller per subscription, negative on a run without first-hop loss.
The counters here come from a live server after a known pattern, not from a hand-written dict,
so the test sees exactly the shape the benchmark reads.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rlbridge.bench.load import Phase, Run, Settings, first_hop_lost, totals_line
from rlbridge.wire import Batch, TopicAck, TopicConnect, Value

F64 = "std_msgs/msg/Float64"


def _values(client: Any, n: int) -> int:
    got = 0
    while got < n:
        packet = client.recv()
        if isinstance(packet, Value):
            got += 1
        elif isinstance(packet, Batch):
            got += len(packet.values)
    return got


def _connect(client: Any, *requests: TopicConnect) -> None:
    client.send(*requests)
    for _ in requests:
        client.expect(TopicAck)


def _run(stats: dict[str, Any], sent: int, received: int) -> Run:
    phase = Phase("after", 1.0, 0.0, 0.0, 0.0, [0], stats, stats)
    return Run(Settings(), [phase], [{"sent": sent, "received": received, "lost_seq": 0}],
               0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))


def test_first_hop_counts_only_publish_gaps(raw_tcp: Callable[..., Any]) -> None:
    # A load client: two channels published and subscribed back; and a consumer of both.
    client, consumer = raw_tcp(), raw_tcp()
    client.hello("load-0")
    consumer.hello("consumer")
    _connect(consumer, *(TopicConnect(c, "subscribe", f"/totals/c{c}", F64, transport="tcp")
                         for c in (1, 2)))
    _connect(client,
             *(TopicConnect(c, "publish", f"/totals/c{c}", F64, transport="tcp") for c in (1, 2)),
             *(TopicConnect(10 + c, "subscribe", f"/totals/c{c}", F64, transport="tcp")
               for c in (1, 2)))
    # Channel 1: values 2 and 3 were written but never reached the server (a gap of 2).
    client.send(Value(1, 0, 0, 0.0), Value(1, 1, 0, 1.0), Value(1, 4, 0, 4.0),
                Batch(2, 0, [0, 0, 0], [0.0, 1.0, 2.0]))
    received = _values(client, 6)
    assert _values(consumer, 6) == 6
    stats = client.stats()  # same connection as the values: they are counted by now

    channels = [c for s in stats["sessions"] for c in s["channels"].values()]
    assert sorted(c["lost"] for c in channels if c["direction"] == "subscribe") == [-1] * 4

    run = _run(stats, sent=8, received=received)
    assert first_hop_lost(run) == 2
    assert ("8 values written, 6 delivered to the subscribing channels, 2 not delivered "
            "(25.00 %), of which 2 never reached the server") in totals_line(run)


def test_no_loss_is_zero_not_minus_the_subscriptions(raw_tcp: Callable[..., Any]) -> None:
    client = raw_tcp()
    client.hello("load-0")
    _connect(client, TopicConnect(1, "publish", "/totals/clean", F64, transport="tcp"),
             TopicConnect(2, "subscribe", "/totals/clean", F64, transport="tcp"))
    client.send(Batch(1, 0, [0] * 5, [1.0] * 5))
    received = _values(client, 5)
    run = _run(client.stats(), sent=5, received=received)
    assert first_hop_lost(run) == 0
    assert "of which 0 never reached the server" in totals_line(run)


def test_gaps_are_read_after_the_drain_when_the_run_has_them(
        raw_tcp: Callable[..., Any]) -> None:
    # A gap is counted when the value after it arrives: behind a deep queue that is after the
    # last phase, so the run's counters from after the clients' drain are the ones that count.
    client = raw_tcp()
    client.hello("load-0")
    _connect(client, TopicConnect(1, "publish", "/totals/late", F64, transport="tcp"),
             TopicConnect(2, "subscribe", "/totals/late", F64, transport="tcp"))
    client.send(Value(1, 0, 0, 0.0))
    _values(client, 1)
    at_phase_end = client.stats()
    client.send(Value(1, 3, 0, 3.0))  # values 1 and 2 were lost before it
    _values(client, 1)
    run = _run(at_phase_end, sent=4, received=2)
    assert first_hop_lost(run) == 0
    run.final_stats = client.stats()
    assert first_hop_lost(run) == 2
    assert "of which 2 never reached the server (its sequence gaps, once the clients had " \
           "drained)" in totals_line(run)

"""Where the load benchmark's values were lost: the kernel's per-socket drops, and the sum.

The drop counter is read from ``/proc/<pid>/net/udp`` for a real socket that the kernel really
overflowed: a receiver with the smallest buffer that nobody reads, and datagrams sent to it
over loopback until some are dropped (on loopback the sender is never blocked by the
receiver's buffer: what does not fit is dropped and counted on the receiving socket).
"""

from __future__ import annotations

import os
import socket
import sys

import pytest

from rlbridge.bench.load_sockets import parse_proc_net_udp, udp_drops, udp_queued, udp_sockets
from rlbridge.bench.load_stages import KernelDrops, stage_table, stages
from waiting import wait_until

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/net/udp")


@linux
def test_a_full_receive_buffer_is_counted_on_its_socket() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1)  # the kernel's minimum
        rx.bind(("127.0.0.1", 0))
        port = rx.getsockname()[1]
        mine = [s for s in udp_sockets(os.getpid()) if s.local_port == port]
        assert len(mine) == 1
        before = udp_drops([os.getpid()])
        sent = 200
        for _ in range(sent):
            tx.sendto(b"x" * 512, ("127.0.0.1", port))
        # What fitted waits to be read (loopback delivers in a softirq: normally already done).
        wait_until(lambda: udp_queued(os.getpid()) > 0, "datagrams queued on the socket")
        rx.settimeout(0.5)  # read what fitted; a deferred softirq has time to deliver
        read = 0
        try:
            while True:
                rx.recv(2048)
                read += 1
        except TimeoutError:
            pass
        (after,) = [s for s in udp_sockets(os.getpid()) if s.local_port == port]
        assert 0 < after.drops < sent
        assert after.rx_queue == 0  # all read
        assert udp_drops([os.getpid()]) - before == after.drops
        assert read + after.drops == sent  # every datagram either queued or counted


def test_proc_net_udp_lines_are_parsed() -> None:
    text = ("   sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid"
            "  timeout inode ref pointer drops\n"
            "  101: 0100007F:A3F1 00000000:0000 07 00000000:00000500 00:00000000 00000000     0"
            "        0 4242 2 0000000000000000 17\n")
    (s,) = parse_proc_net_udp(text).values()
    assert (s.inode, s.local_port, s.rx_queue, s.drops) == (4242, 0xA3F1, 0x500, 17)


def test_the_stages_add_up_to_what_was_written() -> None:
    results = [{"sent": 1000, "received": 950, "lost_seq": 10, "overwritten": 5},
               {"sent": 1000, "received": 990, "lost_seq": 0, "overwritten": 0}]
    st = stages(results, hop1_gaps=30, server_dropped=4, skipped=70,
                kernel=KernelDrops(server=3, clients=1))
    assert (st.written, st.delivered, st.publisher, st.hop1, st.server, st.hop2) == (
        2000, 1940, 5, 30, 4, 10)
    assert st.in_flight == 11
    assert st.publisher + st.hop1 + st.server + st.hop2 + st.in_flight == (
        st.written - st.delivered)
    table = stage_table(st, send_errors=2)
    assert "3 datagrams dropped by the kernel; refused by the client's own socket: 2" in table
    assert "| 30 | 1.500 |" in table
    assert "70 values the clients' processes skipped" in table
    assert KernelDrops(5, 7) - KernelDrops(2, 3) == KernelDrops(3, 4)

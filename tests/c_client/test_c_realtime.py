"""The real-time rule of the C client, proven by the kernel (issue 28, point 6).

``rt_seccomp`` (clients/c/tests/rt_seccomp.c) runs a 1 kHz loop that writes to 10 publish
channels (even ones UDP, odd ones TCP) and reads two subscriptions (the server's echo of two
of them: the newest value, and every value over TCP) under a seccomp filter installed on the
loop thread only, which kills the process on any system call but ``clock_nanosleep`` and
``clock_gettime``; the library's I/O thread streams the values to a real ``rlbridge serve``.
The program must run to its end and exit 0, a Python SDK subscriber must receive every value
of every channel, in order, and the loop must have read its own values back. The negative
control makes one ``write(2)`` from the same loop and must be killed by SIGSYS: the filter is
there and enforced.
"""

from __future__ import annotations

import re
import signal
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path

from rlbridge import Bridge

CHANNELS = 10
COUNT = 3000  # 3 s at 1 kHz
RATE_HZ = 1000
WAIT = 60.0
FLOAT64 = "std_msgs/msg/Float64"

Server = Callable[..., tuple[int, subprocess.Popen[str]]]


def _rt_seccomp(c_build: Path, port: int, prefix: str, *extra: str
                ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(c_build / "rt_seccomp"), "127.0.0.1", str(port), prefix,
                           str(CHANNELS), str(COUNT), str(RATE_HZ), *extra],
                          capture_output=True, text=True, timeout=120, check=False)


def test_the_loop_runs_to_its_end_under_the_filter(c_build: Path, cli_server: Server) -> None:
    port, _ = cli_server()
    prefix = "/rt_seccomp_"
    with Bridge.connect("127.0.0.1", port, timeout=10.0) as bridge:
        channels = [bridge.subscribe(f"{prefix}{i}", FLOAT64,
                                     transport="tcp" if i % 2 else "udp",
                                     blocking=True, buffer_size=COUNT)
                    for i in range(CHANNELS)]
        got: list[list[float]] = [[] for _ in range(CHANNELS)]

        def read_all(i: int) -> None:  # ends at COUNT values or at the first silent WAIT
            for _ in range(COUNT):
                got[i].append(channels[i].read(timeout=WAIT))

        readers = [threading.Thread(target=read_all, args=(i,), daemon=True)
                   for i in range(CHANNELS)]
        for reader in readers:
            reader.start()
        run = _rt_seccomp(c_build, port, prefix)
        for reader in readers:
            reader.join(timeout=WAIT + 10)
    assert run.returncode == 0, run.stderr
    assert "filter installed on the loop thread" in run.stderr
    assert f"{COUNT} values x {CHANNELS} channels written, {COUNT * CHANNELS} sent" in run.stderr
    for i in range(CHANNELS):
        assert got[i] == [float(v) for v in range(COUNT)], f"channel {i}: {len(got[i])} values"
    read_back = re.search(r"read back (\d+) new latest values, (\d+) FIFO values in order",
                          run.stderr)
    assert read_back is not None, run.stderr
    assert int(read_back[1]) > 0
    assert int(read_back[2]) == COUNT


def test_one_forbidden_call_in_the_loop_is_killed(c_build: Path, cli_server: Server) -> None:
    port, _ = cli_server()
    run = _rt_seccomp(c_build, port, "/rt_forbidden_", "--forbidden")
    assert "filter installed on the loop thread" in run.stderr  # it got as far as the loop
    assert run.returncode == -signal.SIGSYS, (run.returncode, run.stderr)
    assert "loop done" not in run.stderr

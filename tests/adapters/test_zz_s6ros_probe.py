"""TEMPORARY instrumentation (s6ros): where do the node->client flood's values go?"""
from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator

import pytest
import reach_netns
from reach_netns import World, world, LoggedProcess, in_namespace, rlbridge_argv, SERVING, PEER


def _start_server(namespace, env, node_name):
    server = LoggedProcess(in_namespace(namespace, [
        *rlbridge_argv(), "--log-level", "info", "serve", "--port", "0", "--adapter", "ros2",
        "--node-name", node_name, "--timeout-ms", "10000"]), env, watch=SERVING)
    return server, int(server.wait_ready().group(1))


reach_netns.start_server = _start_server
HB = os.environ.get("S6_HB_MS")
XML = """<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com"><profiles>
<data_writer profile_name="s6w" is_default_profile="true"><times>
<heartbeat_period><sec>0</sec><nanosec>%d</nanosec></heartbeat_period>
</times></data_writer></profiles></dds>
"""

pytestmark = [pytest.mark.ros2, pytest.mark.netem, pytest.mark.timeout(240)]
INT64 = "std_msgs/msg/Int64"
N = 20_000


@pytest.fixture(scope="module")
def flood_world(tmp_path_factory: pytest.TempPathFactory) -> Iterator[World]:
    with world("flood", tmp_path_factory.mktemp("ros_log")) as made:
        yield made


def chstats(sdk, ch):
    return sdk.server_stats()["session"]["channels"][str(ch.channel_id)]


@pytest.mark.parametrize("rep", range(int(os.environ.get("S6_REPS", "1"))))
def test_probe(flood_world: World, rep: int) -> None:
    sdk = flood_world.connect("flood-sdk")
    info = {"rep": rep, "py": os.sys.version[:5]}
    try:
        ch = sdk.subscribe(f"/flood/down{rep}", INT64, transport="tcp", blocking=True, buffer_size=4 * N)
        env = dict(flood_world.env)
        if HB:
            with open("/tmp/s6ros-hb.xml", "w") as f:
                f.write(XML % (int(HB) * 1_000_000))
            env["FASTDDS_DEFAULT_PROFILES_FILE"] = "/tmp/s6ros-hb.xml"
        import re, sys
        peer = LoggedProcess(in_namespace(flood_world.namespace, [sys.executable, str(PEER), "flood", f"/flood/down{rep}", str(N)]), env, stdin=True, watch=re.compile(r"^probes (\d+)"))
        info["hb"] = HB
        received, times = [], []
        try:
            first = ch.read(timeout=60)
            received, times = [first], [time.monotonic()]
            peer.proc.stdin.write("go\n"); peer.proc.stdin.flush()
            t_go = time.monotonic()
            probes = int(peer.wait_ready().group(1))
            info["probes_line"] = peer.match.group(0) if peer.match else None
            info["pubtime"] = round(time.monotonic() - t_go, 2)
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                got = ch.read_many()
                if got:
                    received += got; times += [time.monotonic()] * len(got)
                    continue
                try:
                    received.append(ch.read(timeout=2.0)); times.append(time.monotonic())
                except TimeoutError:
                    if "quiet" not in info:
                        st = chstats(sdk, ch)
                        info["quiet"] = {"delivered": len(received) - 1, "ros_lost": st["ros_lost"], "values_out": st["values_out"], "sum": len(received) - 1 + st["ros_lost"]}
                    try:
                        received.append(ch.read(timeout=12.0)); times.append(time.monotonic())
                    except TimeoutError:
                        break
        except Exception as exc:
            info["err"] = f"{type(exc).__name__}: {exc} state={sdk.state} reason={sdk.close_reason} peer_rc={peer.proc.poll()} log={peer.log[-400:]!r}"
            probes = 0
            first = received[0] if received else 0
        finally:
            peer.stop()
        try:
            stats = chstats(sdk, ch)
        except Exception as exc:
            stats = {"ros_lost": -99999, "exc": repr(exc)}
        expected = (probes + first) + N
        lost = stats["ros_lost"]
        pauses = sorted(((times[i] - times[i - 1], received[i - 1], received[i]) for i in range(1, len(times))), reverse=True)[:2]
        info.update(first=first, probes=probes, expected=expected, delivered=len(received) - 1, lost=lost,
                    diff=expected - (len(received) - 1 + lost), last=received[-1] if received else None,
                    pauses=[(round(p, 3), a, b) for p, a, b in pauses], values_out=stats.get("values_out"),
                    dropped=stats.get("dropped"))
        line = "S6PROBE " + json.dumps(info)
        print(line)
        with open("/tmp/s6ros-probe.log", "a") as f:
            f.write(line + "\n")
    finally:
        sdk.close()

"""``rlbridge stats`` (table and --json) and ``serve --metrics-port`` against a live server."""

from __future__ import annotations

import json
import subprocess
import urllib.request
from collections.abc import Callable, Sequence
from typing import Any

F64 = "std_msgs/msg/Float64"


def test_stats_table_json_and_metrics(cli: Any, cli_server: Callable[..., Any],
                                      free_port: Callable[[], int],
                                      stats_over_tcp: Callable[[int], dict[str, Any]],
                                      topics_of: Callable[[int], Sequence[str]],
                                      wait_until: Callable[..., Any]) -> None:
    mport = free_port()
    port, _server = cli_server("--metrics-port", str(mport))
    echo = cli.popen("topic", "echo", "/cli/stats", F64, "--transport", "tcp", "--count", "100",
                     "--port", str(port))
    wait_until(lambda: echo.poll() is None and "/cli/stats" in topics_of(port),
               timeout=30, what="the echo to subscribe")
    pub = cli.run("topic", "pub", "/cli/stats", F64, "2.5", "--rate", "200", "--count", "5",
                  "--transport", "tcp", "--port", str(port))
    assert pub.returncode == 0, pub.stderr

    def echo_session() -> dict[str, Any] | None:
        for s in stats_over_tcp(port)["sessions"]:
            if s["name"] == "rlbridge-topic-echo" and s["values_out"] == 5:
                return s
        return None

    wait_until(echo_session, timeout=30, what="the echo session to have sent 5 values")
    table = cli.run("stats", "--port", str(port))
    assert table.returncode == 0, table.stderr
    lines = table.stdout.splitlines()
    assert echo.poll() is None, "the echo exited early"
    assert any("rlbridge-topic-echo" in line for line in lines), table.stdout
    assert lines[0].startswith("server: sessions ")
    assert "values_in 5" in lines[0]
    header = next(i for i, line in enumerate(lines)
                  if line.startswith("ID") and "rlbridge-topic-echo" in lines[i + 1])
    assert lines[header].split() == ["ID", "NAME", "STATE", "RTT_US", "PKTS_IN", "BYTES_IN",
                                     "BYTES_OUT", "VALUES_IN", "VALUES_OUT", "DROPPED", "LATE",
                                     "MALFORMED", "ROS_LOST"]
    session_row = lines[header + 1].split()
    assert session_row[1:3] == ["rlbridge-topic-echo", "connected"]
    assert session_row[8:10] == ["5", "0"]  # values out, dropped
    channel_row = lines[header + 3].split()
    assert channel_row[:4] == ["1", "subscribe", "tcp", "/cli/stats"]
    assert channel_row[5:7] == ["5", "0"]  # values out, dropped
    as_json = cli.run("stats", "--json", "--port", str(port))
    assert as_json.returncode == 0, as_json.stderr
    body = json.loads(as_json.stdout)
    assert body["server"]["values_in"] == 5
    echo_stats = next(s for s in body["sessions"] if s["name"] == "rlbridge-topic-echo")
    assert echo_stats["channels"]["1"]["values_out"] == 5
    with urllib.request.urlopen(f"http://127.0.0.1:{mport}/metrics", timeout=30) as resp:
        text = resp.read().decode()
    assert "rlbridge_values_in_total 5" in text.splitlines()
    echo.kill()
    echo.communicate(timeout=30)


def test_bad_metrics_port_is_one_line(cli: Any) -> None:
    result = cli.run("serve", "--port", "0", "--metrics-port", "70000")
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "rlbridge: error: --metrics-port: Input should be less than or equal to 65535"]
    assert isinstance(result, subprocess.CompletedProcess)

"""``Bridge.close()`` over a lossy link (real kernel TCP and UDP; needs root).

The client's goodbye after a UDP burst goes over UDP, behind the datagrams, and close() waits
for the server to hang up (client/session/goodbye.py). On a link that drops 30 % of the
client's packets a single goodbye datagram would be lost in about a third of the closes, and
close() would give up at its bound; resent while waiting, it gets through. Asserted is the
mechanism: five closes in a row, each confirmed by the server's hang-up (no fallback at the
bound logged, nothing counted as unconfirmed), each within its bound.
"""

from __future__ import annotations

import json
import sys
import textwrap

import pytest

from rlbridge.netem import EmulatedLink, Impairment, emulator_unavailable_reason

pytestmark = [pytest.mark.netem, pytest.mark.timeout(120)]

PORT = 7411
CLOSES = 5

CLIENT = textwrap.dedent("""
    import json, logging, sys, time
    from rlbridge import Bridge, ConnectionFailed
    host, port, closes = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    said = []
    class Catch(logging.Handler):
        def emit(self, record):
            said.append(record.getMessage())
    client_log = logging.getLogger("rlbridge.client")
    client_log.setLevel(logging.INFO)
    client_log.addHandler(Catch(logging.INFO))
    results = []
    for run in range(closes):
        deadline = time.monotonic() + 20
        while True:
            try:
                bridge = Bridge.connect(host, port, timeout=2.0, reconnect=False)
                break
            except ConnectionFailed:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        out = bridge.publish(f"/goodbye/lossy{run}", "std_msgs/msg/Int32", transport="udp")
        for i in range(200):
            out.write(i)
        started = time.monotonic()
        bridge.close()
        results.append({"seconds": time.monotonic() - started, "lost": out.health().lost})
    print(json.dumps({"closes": results, "gave_up": [m for m in said if "closing:" in m]}))
""")


@pytest.fixture(scope="module", autouse=True)
def _require_emulator() -> None:
    reason = emulator_unavailable_reason()
    if reason is not None:
        pytest.skip(f"network emulator unavailable: {reason}")


def test_goodbye_over_a_lossy_link_is_resent_until_the_server_hangs_up() -> None:
    with EmulatedLink(a_to_b=Impairment(delay_ms=5.0),
                      b_to_a=Impairment(delay_ms=5.0, loss_pct=30.0),
                      seed=11, max_lifetime_s=110.0) as link:
        server = link.popen("a", [sys.executable, "-m", "rlbridge.cli", "serve", "--host",
                                  link.addr_a, "--port", str(PORT), "--heartbeat-ms", "100",
                                  "--timeout-ms", "5000", "--insecure"])
        try:
            client = link.popen("b", [sys.executable, "-c", CLIENT, link.addr_a, str(PORT),
                                      str(CLOSES)], stdout=-1, stderr=-1, text=True)
            out, err = client.communicate(timeout=90)
            assert client.returncode == 0, err
        finally:
            server.terminate()
            server.wait(10)
    result = json.loads(str(out).strip().splitlines()[-1])
    print(result)
    assert result["gave_up"] == []  # neither fell back at the bound nor counted a value
    assert len(result["closes"]) == CLOSES
    for close in result["closes"]:
        assert close["seconds"] < 2.0 + 10.0  # its bound (connect's timeout), generously

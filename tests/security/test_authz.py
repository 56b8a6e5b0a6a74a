"""Per-client authorization from the key file: topic globs per direction, and Stats visibility.

Live server, SDK clients: a topic-connect outside a client's allow-list gets a TopicError that
names the client, the topic and what it may use, is counted, and costs nothing else; Stats
shows a client its own session only, unless its line says ``stats=all``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from rlbridge import ErrorCode, Psk, RemoteError, Tls
from rlbridge.client.bridge import Bridge
from rlbridge.server import ServerThread
from rlbridge.tls.certs import issue, make_ca

F64 = "std_msgs/msg/Float64"
ROBOT, OPERATOR, ANYONE = (bytes([n]) * 32 for n in (1, 2, 3))


@pytest.fixture
def ruled_server(make_server: Callable[..., ServerThread], tmp_path: Path) -> ServerThread:
    path = tmp_path / "keys"
    path.write_text(
        f"robot    {ROBOT.hex()}     publish=/robot/*,/cmd_vel subscribe=/state/*\n"
        f"operator {OPERATOR.hex()}  stats=all\n"
        f"*        {ANYONE.hex()}    publish= subscribe=/status/*  # everyone else\n")
    path.chmod(0o600)
    return make_server(psk_file=path)


def counters(srv: ServerThread) -> dict[str, int]:
    assert srv.server.registry is not None
    return dict(srv.server.registry.ctx.counters)


def test_topics_outside_the_allow_list_are_refused_and_counted(ruled_server: ServerThread
                                                              ) -> None:
    port = ruled_server.port
    with Bridge.connect("127.0.0.1", port, name="robot", security=Psk(key=ROBOT.hex()),
                        reconnect=False) as robot:
        robot.publish("/robot/arm/cmd", F64)
        robot.publish("/cmd_vel", "geometry_msgs/msg/Twist", None)
        robot.subscribe("/state/joints", F64)
        with pytest.raises(RemoteError, match="'robot' may not publish to /other") as info:
            robot.publish("/other", F64)
        assert info.value.code == ErrorCode.NOT_ALLOWED
        assert "/robot/*, /cmd_vel" in info.value.reason
        with pytest.raises(RemoteError, match="may not subscribe to /robot/arm/cmd"):
            robot.subscribe("/robot/arm/cmd", F64)
        out = robot.publish("/robot/still_fine", F64)  # the session goes on
        out.write(1.0)
        robot.send(wait=True)
        assert robot.server_stats()["session"]["topics_refused"] == 2
    with Bridge.connect("127.0.0.1", port, name="visitor", security=Psk(key=ANYONE.hex()),
                        reconnect=False) as visitor:
        visitor.subscribe("/status/battery", F64)
        with pytest.raises(RemoteError, match="without a proven name may not publish"):
            visitor.publish("/status/battery", F64)
    with Bridge.connect("127.0.0.1", port, name="robot-impostor", security=Psk(key=ANYONE.hex()),
                        reconnect=False) as impostor, \
            pytest.raises(RemoteError, match="may not publish"):  # the default's rules
        impostor.publish("/robot/arm/cmd", F64)
    assert counters(ruled_server)["topic_not_allowed"] == 4


def test_stats_show_other_sessions_only_to_who_may_see_them(ruled_server: ServerThread) -> None:
    port = ruled_server.port
    with Bridge.connect("127.0.0.1", port, name="robot", security=Psk(key=ROBOT.hex()),
                        reconnect=False) as robot, \
            Bridge.connect("127.0.0.1", port, name="operator", security=Psk(key=OPERATOR.hex()),
                           reconnect=False) as operator:
        mine = robot.server_stats()
        assert [s["name"] for s in mine["sessions"]] == ["robot"]
        assert mine["session"]["identity"] == "robot"
        everyone = operator.server_stats()
        assert {s["name"] for s in everyone["sessions"]} == {"robot", "operator"}


def test_a_certificate_name_carries_its_rules(make_server: Callable[..., ServerThread],
                                             tmp_path: Path) -> None:
    ca = make_ca()
    ca.write(tmp_path / "ca.crt", tmp_path / "ca.key")
    issue("localhost", names=["127.0.0.1"], ca=ca).write(tmp_path / "s.crt", tmp_path / "s.key")
    issue("camera", ca=ca, client=True).write(tmp_path / "c.crt", tmp_path / "c.key")
    rules = tmp_path / "access"
    rules.write_text("camera - publish=/camera/*\n* - publish= subscribe=\n")
    rules.chmod(0o600)
    srv = make_server(tls_cert=tmp_path / "s.crt", tls_key=tmp_path / "s.key",
                      tls_client_ca=tmp_path / "ca.crt", psk_file=rules)
    with Bridge.connect("127.0.0.1", srv.port, security=Tls(ca=tmp_path / "ca.crt",
                                                            client_cert=(tmp_path / "c.crt",
                                                                         tmp_path / "c.key")),
                        reconnect=False) as camera:
        camera.publish("/camera/image_mean", F64)
        with pytest.raises(RemoteError, match="'camera' may not publish to /cmd"):
            camera.publish("/cmd", F64)
        assert [s["identity"] for s in camera.server_stats()["sessions"]] == ["camera"]


def test_an_open_server_has_no_rules_and_shows_every_session(make_server: Callable[
        ..., ServerThread]) -> None:
    srv = make_server()
    with Bridge.connect("127.0.0.1", srv.port, name="a", reconnect=False) as a, \
            Bridge.connect("127.0.0.1", srv.port, name="b", reconnect=False):
        a.publish("/anything/at_all", F64)
        assert {s["name"] for s in a.server_stats()["sessions"]} == {"a", "b"}


def test_a_refusal_quoting_a_long_rule_arrives_cut(make_server: Callable[..., ServerThread],
                                                   tmp_path: Path) -> None:
    """A NOT_ALLOWED reason quotes the client's rules; a long rule made it longer than a
    reason may be, and the client took the TopicError for malformed and waited out its
    patience. The server cuts it, so the refusal arrives as one."""
    rule = ",".join(f"/state/sensor_{n:03d}/*" for n in range(80))
    path = tmp_path / "keys"
    path.write_text(f"robot {ROBOT.hex()} publish= subscribe={rule}\n")
    path.chmod(0o600)
    srv = make_server(psk_file=path)
    with Bridge.connect("127.0.0.1", srv.port, name="robot", security=Psk(key=ROBOT.hex()),
                        reconnect=False) as robot:
        with pytest.raises(RemoteError, match="'robot' may not subscribe to /other") as info:
            robot.subscribe("/other", F64)
        assert info.value.code == ErrorCode.NOT_ALLOWED
        assert len(info.value.reason) == 1024
        assert info.value.reason.endswith("\u2026")
        assert "/state/sensor_000/*" in info.value.reason
        robot.subscribe("/state/sensor_079/x", F64)  # the session goes on

"""The link's reports: a session's end is final for that session, a reconnect stays ``lost``
for the owner until its channels are bound again."""

from __future__ import annotations

from rlbridge.client.session.link_report import LinkReport
from rlbridge.wire.link import LinkState

C, D, L = LinkState.CONNECTED, LinkState.DEGRADED, LinkState.LOST


def told() -> tuple[LinkReport, list[tuple[LinkState, str]]]:
    report, seen = LinkReport(), []
    report.on_change = lambda state, reason: seen.append((state, reason))
    return report, seen


def test_an_ended_session_cannot_report_the_link_back_up() -> None:
    report, seen = told()
    report.session_started(1, told=True)
    report.update(D, "quiet", 1)
    report.session_ended("server closed the session: server shutting down")
    report.update(C, "heard from the server", 1)  # the goodbye's receive thread, too late
    assert seen == [(D, "quiet"), (L, "server closed the session: server shutting down")]
    assert report.state is L


def test_a_reconnected_session_is_told_only_once_bound_again() -> None:
    report, seen = told()
    report.session_started(1, told=True)
    report.session_ended("cut")
    report.session_started(2, told=False)
    report.update(D, "quiet", 2)  # recorded, not told: the channels are not bound yet
    report.update(C, "heard", 1)  # a stale session: ignored altogether
    assert seen == [(L, "cut")]
    assert report.state is D
    report.restored("reconnected: session 2")
    report.restored("again")  # once
    report.update(C, "heard", 2)
    assert seen == [(L, "cut"), (D, "reconnected: session 2"), (C, "heard")]


def test_restored_after_the_session_ended_tells_nothing() -> None:
    report, seen = told()
    report.session_started(2, told=False)
    report.session_ended("cut again")
    report.restored("reconnected: session 2")
    assert seen == [(L, "cut again")]

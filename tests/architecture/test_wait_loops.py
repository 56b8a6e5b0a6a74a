"""Tests wait one way: ``wait_until`` (tests/waiting.py), not a deadline loop of their own.

A hand-written loop (``deadline = time.monotonic() + 5`` and ``while time.monotonic() <
deadline: ... sleep``) is where waits go wrong: one forgets to fail at the deadline and the test
goes on as if the condition held, another fails without saying what it waited for, a third
spins without a pause. This check finds a loop (``while`` or ``for``) that reads the clock in
its condition, compares the clock inside its body (``if time.monotonic() > deadline``) or
counts down to a deadline (``left = deadline - time.monotonic()``), in any test module but
tests/waiting.py. Code in strings (scripts a test runs in another interpreter) is not parsed.

Loops that are not waits are listed in ``ALLOWED`` with the reason: a load that runs for a
fixed time, an observation window, a protocol client's own I/O deadline, a peer program that
runs without tests/ on its path. An entry that no longer matches a loop fails too. The last
test checks that the helpers the loops became still say what they waited for.
"""

from __future__ import annotations

import ast
import functools
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from waiting import WAIT, assert_running, poll_until, wait_until, wait_until_ok

TESTS = Path(__file__).resolve().parents[1]
CLOCKS = {"monotonic", "perf_counter", "time", "monotonic_ns", "perf_counter_ns", "time_ns"}

#: ``(path under tests/, qualified function name)`` -> why its clock loop is not a wait.
ALLOWED: dict[tuple[str, str], str] = {
    ("adapters/ros2_peer.py", "stream"):
        "paces a stream on an absolute schedule (sleep to the next slot): no wait",
    ("adapters/ros2_peer.py", "latency_pub"):
        "a peer program in a process of its own, run by other ROS releases too; it imports "
        "nothing of the tests and waits for its subscriber as a plain rclpy node would",
    ("adapters/ros2_reach_peer.py", "latched"):
        "a peer program in a network namespace; its outcome is its exit code and printout, "
        "which the test checks",
    ("adapters/ros2_reach_peer.py", "count_gaps"):
        "a peer program in a network namespace: counts until the last message or a quiet "
        "period and prints the counts, which the test checks",
    ("adapters/test_ros2_peer.py",
     "test_publish_flood_does_not_starve_the_executor.publish_flat_out"):
        "a load: publishes flat out for 1 s while the peer streams in",
    ("c_client/test_c_credit.py", "Peer.read"):
        "a frame reader: one recv per turn against the caller's timeout, None when nothing "
        "came (the callers assert on it)",
    ("c_client/test_c_credit.py", "test_rlb_pub_sends_only_what_the_credit_allows"):
        "an observation window: reads for 1 s to show that nothing beyond the credit comes",
    ("client/test_loss_feedback.py",
     "test_bundled_flood_loss_is_reported_per_channel_as_the_server_counted"):
        "a load: floods for the 2 s the server's loop is stalled (the wait after it is "
        "waiting.poll_until)",
    ("hrt/pattern_support.py", "collect"):
        "collects values with blocking reads and returns what came: the callers compare the "
        "list, which shows a shortfall value by value",
    ("interop/independent_client.py", "IndependentClient.pump"):
        "an independent protocol client: its I/O deadline is the client's own (it answers "
        "False, as a client would), not a test's wait",
    ("interop/independent_client.py", "IndependentClient.connect_udp"):
        "an independent protocol client: retransmits its UDP hello until answered and raises "
        "TimeoutError, as the protocol document says a client does",
    ("interop/independent_client.py", "IndependentClient.bind"):
        "an independent protocol client: retransmits a UDP TopicConnect until answered and "
        "raises TimeoutError, as the protocol document says a client does",
}


def _is_clock(node: ast.AST) -> bool:
    """``time.monotonic()`` and its kin (or a bare ``monotonic()`` imported from time)."""
    if not isinstance(node, ast.Call) or node.args:
        return False
    func = node.func
    if isinstance(func, ast.Attribute):
        return (func.attr in CLOCKS and isinstance(func.value, ast.Name)
                and func.value.id == "time")
    return isinstance(func, ast.Name) and func.id in CLOCKS - {"time"}


def _reads_clock(node: ast.AST) -> bool:
    return any(_is_clock(n) for n in ast.walk(node))


def _body_nodes(loop: ast.While | ast.For) -> Iterator[ast.AST]:
    """Every node of the loop's body and ``else``, not entering functions or loops there."""
    todo: list[ast.AST] = [*loop.body, *loop.orelse]
    while todo:
        node = todo.pop()
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda
                      | ast.While | ast.For):
            continue  # a loop inside is judged by itself
        yield node
        todo.extend(ast.iter_child_nodes(node))


def _is_deadline_loop(loop: ast.While | ast.For) -> bool:
    if isinstance(loop, ast.While) and _reads_clock(loop.test):
        return True
    for node in _body_nodes(loop):
        if isinstance(node, ast.Compare) and _reads_clock(node):
            return True  # if time.monotonic() > deadline: raise / break
        if (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Sub)
                and _is_clock(node.right)):
            return True  # left = deadline - time.monotonic()
    return False


def _deadline_loops(tree: ast.AST) -> Iterator[tuple[str, int]]:
    """``(qualified name of the enclosing function, line)`` of every deadline loop."""
    def walk(node: ast.AST, scope: str) -> Iterator[tuple[str, int]]:
        for child in ast.iter_child_nodes(node):
            inner = scope
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                inner = f"{scope}.{child.name}" if scope else child.name
            if isinstance(child, ast.While | ast.For) and _is_deadline_loop(child):
                yield scope or "<module>", child.lineno
            yield from walk(child, inner)
    return walk(tree, "")


@functools.cache
def _all_deadline_loops() -> dict[tuple[str, str], list[int]]:
    found: dict[tuple[str, str], list[int]] = {}
    for path in sorted(TESTS.rglob("*.py")):
        rel = str(path.relative_to(TESTS))
        if "__pycache__" in path.parts or rel == "waiting.py":
            continue
        for scope, line in _deadline_loops(ast.parse(path.read_text(), filename=str(path))):
            found.setdefault((rel, scope), []).append(line)
    return found


def test_no_test_module_waits_with_a_deadline_loop_of_its_own() -> None:
    offenders = [f"{path}:{line} in {scope}"
                 for (path, scope), lines in _all_deadline_loops().items()
                 if (path, scope) not in ALLOWED for line in lines]
    assert not offenders, (
        "wait with waiting.wait_until (or wait_until_ok), not a deadline loop; a loop that is "
        f"no wait goes in ALLOWED with its reason: {offenders}")


def test_every_allowed_loop_still_exists() -> None:
    found = _all_deadline_loops()
    stale = [f"{path} {scope}" for path, scope in ALLOWED if (path, scope) not in found]
    assert not stale, f"ALLOWED names loops that are gone (remove the entries): {stale}"


def test_the_check_sees_each_shape_of_deadline_loop() -> None:
    """The detector itself: each hand-written shape is found, a wait_until call is not."""
    shapes = [
        "while time.monotonic() < deadline:\n    time.sleep(0.01)",
        "while not ok() and time.monotonic() < deadline:\n    pass",
        "while not ok():\n    assert time.monotonic() < deadline, 'never'",
        "while True:\n    if time.monotonic() > deadline:\n        raise TimeoutError",
        "while (left := deadline - time.monotonic()) > 0:\n    get(left)",
        "while x:\n    left = deadline - time.monotonic()",
        "for line in lines:\n    if time.perf_counter() > deadline:\n        break",
    ]
    for source in shapes:
        assert list(_deadline_loops(ast.parse(f"def f():\n{_indent(source)}"))) == [("f", 2)], \
            source
    fine = ("def f():\n    wait_until(lambda: time.monotonic() > t, 'later')\n"
            "    for v in values:\n        stamps.append(time.monotonic_ns())\n")
    assert list(_deadline_loops(ast.parse(fine))) == []


def _indent(source: str) -> str:
    return "".join(f"    {line}\n" for line in source.splitlines())


def test_the_helpers_say_what_they_waited_for() -> None:
    """What the loops became keeps their failure messages: ``what`` asked at the timeout, the
    last error of an attempt, the exit of a process that a wait needed."""
    got = [1.0]
    with pytest.raises(AssertionError, match=r"waiting for 3 values \(1 came\)"):
        wait_until(lambda: len(got) >= 3, lambda: f"3 values ({len(got)} came)", timeout=0.05)
    assert poll_until(lambda: 0, timeout=0.05) == 0  # the last answer, no failure
    calls: list[int] = []

    def refuse_twice() -> None:  # a success that returns None still ends the wait
        calls.append(1)
        if len(calls) < 3:
            raise ConnectionRefusedError("not yet")

    assert wait_until_ok(refuse_twice, "a session", interval=0) is None
    assert len(calls) == 3
    with pytest.raises(AssertionError, match=r"a session \(the last attempt said: "
                                             r"ConnectionRefusedError\('never'\)\)"):
        wait_until_ok(_refuse, "a session", timeout=0.05, interval=0)
    proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.exit('gone')"],
                            stderr=subprocess.PIPE, text=True)
    proc.wait(WAIT)
    with pytest.raises(AssertionError, match="exited with 1: gone"):
        wait_until_ok(_refuse, "a session", between=lambda: assert_running(proc))


def _refuse() -> None:
    raise ConnectionRefusedError("never")

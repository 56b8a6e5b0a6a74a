"""Every code block of README.md and docs/*.md runs as printed, or says why it cannot.

Which blocks are code
    A fence tagged ``python`` or ``sh`` (``py``, ``bash``, ``shell``, ``console``) is run. A fence
    tagged ``text``, ``json``, ``yaml``, ``toml``, ``ini``, ``csv`` or left untagged shows text
    (output, a layout, data) and is not code. Any other tag (``c``, ``cmake``, ...) is code this
    runner cannot run: such a block must be a fragment.

Markers: an HTML comment on its own line directly above the opening fence (several may stack)
    ``<!-- fragment: why -->``
        The block cannot run alone (a piece of a larger program, a machine set-up, a command
        that runs until Ctrl-C, ...); the reason is required and is what a reader sees in the
        source. Fragments are not run; nothing else skips a block.
    ``<!-- needs: ros2 -->`` (or ``psk``, ``tls``)
        The block runs against that server (below) instead of the default one.

How a block runs
    ``python``: written to ``snippet.py`` in a fresh directory and run there as a script with
    this interpreter (so a ``__main__`` guard and a spawned loop process work as for a user);
    exit status 0 within ``BLOCK_TIMEOUT`` seconds. ``sh``: each line is a command (``\\`` joins
    lines, ``#`` starts a comment), run without a shell in a fresh directory, each must exit 0.
    Allowed commands: ``rlbridge ...`` (a client command such as ``topic pub`` gets
    ``--port <live port>`` unless the line names a port; ``rlbridge serve ...`` is started with
    ``--port 0``, must log that it listens, then gets SIGINT and must exit 0; ``rlbridge demo``,
    ``bench`` and ``netem`` are not run: mark such blocks fragments) and
    ``export NAME=VALUE`` (for the lines after it). Any other command: mark the block a
    fragment.

The address (the one change made to a block)
    The docs write the server as ``192.168.1.10`` or ``127.0.0.1``, port ``7411``. The runner
    replaces ``192.168.1.10`` with ``127.0.0.1`` and the word ``7411`` with the live server's
    port. In a ``needs: tls`` block, a fingerprint (64 hex digits, as ``rlbridge tls init``
    prints it) is replaced with the one of the certificate the runner made.

The servers (real ``rlbridge serve`` processes on loopback, see ``live_server.py``)
    default
        ``rlbridge serve --udp`` (the in-process bus), with a client of it, "the robot", that
        provides the service ``/arm/enable`` (``std_srvs/srv/SetBool``: success = data) and
        publishes a latched (``transient_local``) ``/map`` (``std_msgs/msg/String``).
    ``ros2``
        ``rlbridge serve --adapter ros2 --udp`` on a ROS 2 graph scoped to this machine and run
        (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, a domain id per run),
        with ``tests/docs/docs_ros_peer.py``: node ``controller`` (parameter ``kp`` = 2.0), the
        same ``/arm/enable`` and latched ``/map``, and the action ``/fibonacci``
        (``test_msgs/action/Fibonacci``). Skipped without rclpy.
    ``psk``
        ``rlbridge serve --udp --psk-file robot.key`` in the block's directory, where
        ``robot.key`` holds a fresh key (hex), as ``openssl rand -hex 32`` makes it.
    ``tls``
        ``rlbridge tls init tls/`` in the block's directory, then
        ``rlbridge serve --udp --tls-cert tls/server.crt --tls-key tls/server.key``.
"""

from __future__ import annotations

import os
import re
import secrets
import shlex
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from doc_blocks import PYTHON, SHELL, Block, all_blocks
from live_server import LiveServer, rlbridge_command

BLOCK_TIMEOUT = 90.0  # below pytest's 120 s, so a hung block fails with its own output
DOC_HOST = "192.168.1.10"
DOC_PORT = re.compile(r"\b7411\b")
FINGERPRINT = re.compile(r"\b[0-9a-f]{64}\b")
CLIENT_COMMANDS = frozenset({"topic", "service", "param", "action", "stats", "ping"})
NOT_RUN_COMMANDS = frozenset({"demo", "bench", "netem"})
PEER = Path(__file__).with_name("docs_ros_peer.py")

BLOCKS = all_blocks()
CODE = [b for b in BLOCKS if b.is_code]
RUN = [pytest.param(b, id=b.name, marks=[pytest.mark.slow]
                     + ([pytest.mark.ros2] if "ros2" in b.needs else []))
       for b in CODE if b.fragment is None]


@dataclass
class Server:
    """What a block runs against: the port, the environment, the fingerprint to pin."""

    port: int
    env: dict[str, str] = field(default_factory=lambda: dict(os.environ))
    fingerprint: str | None = None


# -- the servers ---------------------------------------------------------------------------


class Robot:
    """The default server's other client: provides ``/arm/enable``, latches ``/map``."""

    def __init__(self, port: int) -> None:
        from rlbridge import Bridge, QoS

        self.bridge = Bridge.connect("127.0.0.1", port, name="docs-robot")
        self.requests = self.bridge.serve_service("/arm/enable", "std_srvs/srv/SetBool")
        self.map = self.bridge.publish("/map", "std_msgs/msg/String", transport="tcp",
                                       qos=QoS(durability="transient_local", depth=1))
        self.map.write("map v1")
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            try:
                request = self.requests.read(timeout=0.1)
            except TimeoutError:
                continue
            enabled = bool(request.data.get("data"))
            request.reply({"success": enabled, "message": "enabled" if enabled else "disabled"})

    def close(self) -> None:
        self.stop.set()
        self.thread.join(10.0)
        self.bridge.close()


@pytest.fixture(scope="module")
def default_server() -> Iterator[Server]:
    with LiveServer(["--udp"]) as live:
        robot = Robot(live.port)
        try:
            yield Server(live.port)
        finally:
            robot.close()


@pytest.fixture(scope="module")
def ros2_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    pytest.importorskip("rclpy", reason="rclpy is not installed (pip install -e '.[ros2]')")
    pytest.importorskip("test_msgs.action", reason="needs ros-test-msgs")
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           # as tests/adapters/conftest.py: per run, or the one scripts/test.sh gives it
           "ROS_DOMAIN_ID": os.environ.get("RLBRIDGE_TEST_ROS_DOMAIN_ID")
           or str(1 + (os.getpid() + 50) % 100),
           "ROS_LOG_DIR": str(tmp_path_factory.mktemp("ros_log"))}
    env.pop("ROS_STATIC_PEERS", None)
    peer = subprocess.Popen([sys.executable, str(PEER)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert peer.stdout is not None
        ready = peer.stdout.readline().strip()
        assert ready == "ready", f"the docs' ROS peer did not start: {peer.stderr}"
        with LiveServer(["--adapter", "ros2", "--udp"], env=env) as live:
            yield Server(live.port, env=env)
    finally:
        peer.communicate(timeout=60)  # closes its stdin: it stops


@pytest.fixture
def psk_server(tmp_path: Path) -> Iterator[Server]:
    key = tmp_path / "robot.key"
    key.write_text(secrets.token_hex(32) + "\n")
    key.chmod(0o600)
    with LiveServer(["--udp", "--psk-file", str(key)], cwd=tmp_path) as live:
        yield Server(live.port)


@pytest.fixture
def tls_server(tmp_path: Path) -> Iterator[Server]:
    made = subprocess.run([rlbridge_command(), "tls", "init", "tls"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60, check=True)
    found = FINGERPRINT.search(made.stdout + made.stderr)
    assert found, f"rlbridge tls init printed no fingerprint: {made.stdout}{made.stderr}"
    with LiveServer(["--udp", "--tls-cert", "tls/server.crt", "--tls-key", "tls/server.key"],
                    cwd=tmp_path) as live:
        yield Server(live.port, fingerprint=found[0])


ENVIRONMENTS = {"": "default_server", "ros2": "ros2_server", "psk": "psk_server",
                "tls": "tls_server"}


# -- running a block -------------------------------------------------------------------------


def localize(text: str, server: Server) -> str:
    """The documented address -> the live one (and the documented fingerprint -> the real)."""
    text = DOC_PORT.sub(str(server.port), text.replace(DOC_HOST, "127.0.0.1"))
    if server.fingerprint is not None:
        text = FINGERPRINT.sub(server.fingerprint, text)
    return text


def run_python(block: Block, server: Server, cwd: Path) -> None:
    script = cwd / "snippet.py"
    script.write_text(localize(block.code, server), encoding="utf-8")
    proc = subprocess.run([sys.executable, str(script)], cwd=cwd, env=server.env,
                          capture_output=True, text=True, timeout=BLOCK_TIMEOUT, check=False)
    assert proc.returncode == 0, (f"{block.name} failed ({proc.returncode}):\n"
                                  f"{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")


def commands(code: str) -> Iterator[list[str]]:
    """The block's commands as argument lists (``\\`` continues, ``#`` comments)."""
    for line in code.replace("\\\n", " ").splitlines():
        words = shlex.split(line, comments=True)
        if words:
            yield words


def run_command(block: Block, words: list[str], server: Server, cwd: Path,
                env: dict[str, str]) -> None:
    if words[0] == "export":
        for assignment in words[1:]:
            name, _, value = assignment.partition("=")
            env[name] = value
        return
    assert words[0] == "rlbridge", (
        f"{block.name}: the runner runs `rlbridge ...` and `export` lines only, not "
        f"{words[0]!r}: mark the block <!-- fragment: why --> if it cannot run alone")
    verb = next((w for w in words[1:] if not w.startswith("-")), "")
    assert verb not in NOT_RUN_COMMANDS, (
        f"{block.name}: `rlbridge {verb}` is not run here: mark the block a fragment")
    args = [rlbridge_command(), *words[1:]]
    has_port = any(w in ("-p", "--port") or w.startswith("--port=") for w in words)
    if verb == "serve":
        serve_args = words[words.index("serve") + 1:]
        if has_port:
            at = next(i for i, w in enumerate(serve_args) if w in ("-p", "--port"))
            del serve_args[at:at + 2]
        with LiveServer(serve_args, env=env, cwd=cwd) as live:
            status = live.stop()
        assert status == 0, f"{block.name}: {' '.join(words)} exited {status}:\n{live.log}"
        return
    if verb in CLIENT_COMMANDS and not has_port:
        args += ["--port", str(server.port)]
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=BLOCK_TIMEOUT, check=False)
    assert proc.returncode == 0, (f"{block.name}: {' '.join(words)} exited {proc.returncode}:"
                                  f"\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")


def run_shell(block: Block, server: Server, cwd: Path) -> None:
    env = dict(server.env)
    for words in commands(localize(block.code, server)):
        run_command(block, words, server, cwd, env)


# -- the tests -------------------------------------------------------------------------------


@pytest.mark.parametrize("block", RUN)
def test_code_block_runs(block: Block, request: pytest.FixtureRequest, tmp_path: Path) -> None:
    assert block.lang in PYTHON | SHELL, (
        f"{block.name}: a {block.lang!r} block cannot run here: mark it "
        "<!-- fragment: why --> (or show it as text)")
    unknown = block.needs - ENVIRONMENTS.keys()
    assert not unknown, f"{block.name}: unknown needs {sorted(unknown)}"
    assert len(block.needs) <= 1, f"{block.name}: one server per block"
    server: Server = request.getfixturevalue(ENVIRONMENTS[next(iter(block.needs), "")])
    if block.lang in PYTHON:
        run_python(block, server, tmp_path)
    else:
        run_shell(block, server, tmp_path)


@pytest.mark.parametrize("block", [b for b in CODE if b.fragment is not None],
                         ids=lambda b: b.name)
def test_a_fragment_says_why(block: Block) -> None:
    assert block.fragment is not None
    assert len(block.fragment.split()) >= 2, (
        f"{block.name}: <!-- fragment: ... --> needs a reason a reader understands")


def test_markers_are_known() -> None:
    unknown = {f"{b.name}: {key}" for b in BLOCKS for key in b.markers
               if key not in ("fragment", "needs")}
    assert not unknown, f"markers are `fragment` and `needs` only: {sorted(unknown)}"


# -- the runner itself ------------------------------------------------------------------------


def test_localize_changes_the_documented_address_only() -> None:
    server = Server(40123, fingerprint="ab" * 32)
    text = ('Bridge.connect("192.168.1.10", 7411)  # port 74110 stays, 7411 goes\n'
            f'Tls(fingerprint="{"89a78d9b" * 8}")')
    assert localize(text, server) == (
        'Bridge.connect("127.0.0.1", 40123)  # port 74110 stays, 40123 goes\n'
        f'Tls(fingerprint="{"ab" * 32}")')


def test_commands_join_continued_lines_and_drop_comments() -> None:
    code = ("rlbridge topic pub /x std_msgs/msg/Float64 1.5 \\\n    --count 5  # five\n"
            "# a comment line\n\nrlbridge service call /a std_srvs/srv/SetBool '{data: true}'\n")
    assert list(commands(code)) == [
        ["rlbridge", "topic", "pub", "/x", "std_msgs/msg/Float64", "1.5", "--count", "5"],
        ["rlbridge", "service", "call", "/a", "std_srvs/srv/SetBool", "{data: true}"]]


def test_blocks_read_stacked_markers_and_indented_fences(tmp_path: Path) -> None:
    from doc_blocks import blocks

    page = tmp_path / "page.md"
    page.write_text("text\n<!-- fragment: part of a loop -->\n<!-- needs: ros2 -->\n"
                    "```python\nx = 1\n```\n\n- item:\n\n  ```sh\n  rlbridge ping\n  ```\n"
                    "<!-- fragment: not this one -->\n\n```text\nout\n```\n")
    first, second, third = blocks(page)
    assert (first.lang, first.code, first.fragment, first.needs) == \
        ("python", "x = 1\n", "part of a loop", frozenset({"ros2"}))
    assert (second.lang, second.code, second.markers) == ("sh", "rlbridge ping\n", {})
    assert third.markers == {}  # a blank line between marker and fence: not its marker
    assert not third.is_code

"""getting-started.md section 2 runs as written: each pair of commands, bridge then controller,
tracks (the controller is not refused for want of the key the bridge wrote).

Each pair runs in a network namespace of its own (root: ``unshare -n``), so port 7411 is free
and ``--host 0.0.0.0`` reaches nothing but the namespace; 10.203.0.1 (the netem recipe's side A,
and ``<that machine>``) is an address of its loopback. The netem recipe's ``sudo ip netns exec
<ns>`` prefixes are dropped: both sides share the namespace here, and the directory, as the
recipe says they share the directory.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parents[2] / "docs" / "getting-started.md"
ADDRESS = "10.203.0.1"

#: Runs inside the namespace: loopback up with ADDRESS, the bridge, then the controller until
#: it reports tracking (or 60 s), then Ctrl-C to both; prints what each said, as JSON.
DRIVER = r"""
import json, signal, subprocess, sys, time
bridge_cmd, controller_cmd, address = json.loads(sys.argv[1])
subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
subprocess.run(["ip", "addr", "add", f"{address}/32", "dev", "lo"], check=True)
bridge = subprocess.Popen(bridge_cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
controller = subprocess.Popen(controller_cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)
said, tracking = [], False
deadline = time.monotonic() + 60
for line in controller.stdout:
    said.append(line)
    if "state -> tracking" in line:
        tracking = True
        break
    if time.monotonic() > deadline:
        break
for proc in (controller, bridge):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
rest, _ = controller.communicate(timeout=60)
bridge_out, _ = bridge.communicate(timeout=60)
print(json.dumps({"tracking": tracking, "controller": "".join(said) + rest,
                  "bridge": bridge_out}))
"""


def _recipes() -> list[tuple[list[str], list[str]]]:
    """(bridge, controller) argument lists of every pair in section 2."""
    text = DOC.read_text()
    section = text.split("## 2. ", 1)[1].split("\n## 3. ", 1)[0]
    pairs = []
    for block in re.findall(r"```sh\n(.*?)```", section, re.S):
        commands = []
        for line in block.splitlines():
            command = re.sub(r"^sudo ip netns exec <ns [AB]> ", "",
                             line.split("#", 1)[0].strip())
            if command.startswith("rlbridge demo "):
                words = shlex.split(command.replace("<that machine>", ADDRESS))
                commands.append([sys.executable, "-m", "rlbridge", *words[1:]])
        if commands:
            assert len(commands) == 2, block
            pairs.append((commands[0], commands[1]))
    return pairs


def test_section_2_has_the_three_recipes() -> None:
    pairs = _recipes()
    assert len(pairs) == 3
    assert all("--role" in b and "bridge" in b for b, _ in pairs)
    assert all("controller" in c for _, c in pairs)
    assert any("0.0.0.0" in b for b, _ in pairs)
    assert any(ADDRESS in b for b, _ in pairs)


@pytest.mark.netem
@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("unshare") is None,
                    reason="needs root and unshare for a network namespace")
@pytest.mark.parametrize("pair", _recipes(), ids=["loopback", "shared-network", "netem"])
def test_each_recipe_runs_as_written(pair: tuple[list[str], list[str]], tmp_path: Path) -> None:
    bridge, controller = pair
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("RLBRIDGE_PSK", None)
    done = subprocess.run(
        ["unshare", "-n", sys.executable, "-c", DRIVER,
         json.dumps([bridge, controller, ADDRESS])],
        capture_output=True, text=True, timeout=180, cwd=tmp_path, env=env, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    said = json.loads(done.stdout)
    assert said["tracking"], said
    assert "requires a pre-shared key" not in said["controller"], said["controller"]
    keyed = not {"127.0.0.1", "localhost"} & set(bridge) and "--host" in bridge
    assert (tmp_path / "rlbridge-demo.key").exists() == keyed, said["bridge"]

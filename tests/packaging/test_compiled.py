"""The compiled value path (setup.py, rlbridge/_compiled.py): built, it is what runs; asked for,
or stale, the Python files run instead; and a machine that cannot compile still installs.

``RLBRIDGE_TEST_REQUIRE_COMPILED=1`` (scripts/test.sh, whose ``.venv`` compiles) makes a
package that did not compile a failure instead of a skip.
"""

from __future__ import annotations

import importlib.machinery
import json
import os
import subprocess
import sys
import venv
from pathlib import Path

import pytest

from rlbridge._compiled import (
    MODULES,
    NOT_BUILT,
    PURE_ENV,
    SOURCES_FILE,
    STATE,
    decide,
    digest,
    pure_requested,
    source_of,
)

ROOT = Path(__file__).resolve().parents[2]
REQUIRE = (os.environ.get("RLBRIDGE_TEST_REQUIRE_COMPILED") == "1"
           and not pure_requested(os.environ))
SUFFIX = importlib.machinery.EXTENSION_SUFFIXES[0]

#: Imports every compiled module, sends one value through a real server and back, and prints
#: where each module came from and what rlbridge decided.
_PROBE = """
import importlib, json, sys, time
from rlbridge._compiled import MODULES, STATE
from rlbridge.client.bridge import Bridge
from rlbridge.server import ServerConfig, ServerThread

loaders = {m: type(importlib.import_module(m).__spec__.loader).__name__ for m in MODULES}
with ServerThread(ServerConfig(port=0, udp=True)) as srv, \\
        Bridge.connect("127.0.0.1", srv.port, name="probe", timeout=30) as b:
    inbox = b.subscribe("/probe", "std_msgs/msg/Float64", transport="udp")
    out = b.publish("/probe", "std_msgs/msg/Float64", transport="udp")
    got, deadline = [], time.monotonic() + 30
    while not got and time.monotonic() < deadline:
        out.write(1.5)
        time.sleep(0.05)
        got = inbox.read_many()
print(json.dumps({"loaders": loaders, "state": STATE, "got": got}))
"""


def _probe(**env: str) -> dict[str, object]:
    environ = {k: v for k, v in os.environ.items() if k != PURE_ENV} | env
    proc = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                          timeout=90, env=environ, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result: dict[str, object] = json.loads(proc.stdout.splitlines()[-1])
    assert result["got"], "no value came back"
    return result


def _compiled_or_skip() -> None:
    if not STATE.startswith("compiled"):
        if REQUIRE:
            pytest.fail(f"RLBRIDGE_TEST_REQUIRE_COMPILED=1 but the value path is {STATE}; "
                        "`pip install -v -e . 2>&1 | grep 'rlbridge build'` says why")
        pytest.skip(f"the value path is {STATE}")


def test_when_built_the_compiled_modules_are_what_runs() -> None:
    _compiled_or_skip()
    result = _probe()
    assert result["state"] == STATE
    assert result["loaders"] == dict.fromkeys(MODULES, "ExtensionFileLoader")


def test_the_pure_variable_runs_the_python_files() -> None:
    result = _probe(**{PURE_ENV: "1"})
    assert result["loaders"] == dict.fromkeys(MODULES, "SourceFileLoader")
    assert result["state"] in (NOT_BUILT, f"pure Python ({PURE_ENV} is set)")


def _fake_package(root: Path, modules: tuple[str, ...], *, built: tuple[str, ...]) -> Path:
    """Python files for ``modules``; an (empty) extension file beside each of ``built``."""
    for module in modules:
        source = source_of(module, root)
        source.parent.mkdir(parents=True, exist_ok=True)
        source.write_text(f"NAME = {module!r}\n")
        if module in built:
            source.with_name(source.stem + SUFFIX).write_bytes(b"")
    return root


def test_the_decision_follows_the_files(tmp_path: Path) -> None:
    mods = ("rlbridge.wire.a", "rlbridge.csp.b")
    rule = {"suffixes": (SUFFIX,), "modules": mods}
    none = _fake_package(tmp_path / "none", mods, built=())
    assert decide(none, {}, **rule) == (False, NOT_BUILT)

    pkg = _fake_package(tmp_path / "all", mods, built=mods)
    assert decide(pkg, {}, **rule)[1].startswith("pure Python (2 source(s) changed")  # no record
    (pkg / SOURCES_FILE).write_text(json.dumps({m: digest(source_of(m, pkg)) for m in mods}))
    assert decide(pkg, {}, **rule) == (True, "compiled (mypyc, 2 modules)")
    assert decide(pkg, {PURE_ENV: "0"}, **rule)[0] is True
    assert decide(pkg, {PURE_ENV: "1"}, **rule) == (False, f"pure Python ({PURE_ENV} is set)")

    source_of(mods[1], pkg).write_text("NAME = 'edited'\n")  # an edit after the build
    assert decide(pkg, {}, **rule) == (
        False, "pure Python (1 source(s) changed since they were compiled, e.g. "
               "rlbridge.csp.b: pip install -e . compiles them again)")

    half = _fake_package(tmp_path / "half", mods, built=mods[:1])
    assert decide(half, {}, **rule) == (
        False, "pure Python (1 of the 2 compiled modules are missing)")


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_an_install_that_cannot_compile_installs_the_python_package(tmp_path: Path) -> None:
    """``pip install .`` where the C compiler fails (``CC=false``): it installs, pure."""
    venv.create(tmp_path / "venv", with_pip=True)
    python = tmp_path / "venv" / "bin" / "python"
    env = {k: v for k, v in os.environ.items() if k != PURE_ENV} | {"CC": "false"}
    proc = subprocess.run([str(python), "-m", "pip", "install", "-v", "--no-deps", str(ROOT)],
                          capture_output=True, text=True, timeout=850, env=env, check=False)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "rlbridge build: compiling failed" in proc.stdout + proc.stderr
    state = subprocess.run([str(python), "-c", "import rlbridge._compiled as c; print(c.STATE)"],
                           capture_output=True, text=True, timeout=60, check=True, cwd=tmp_path)
    assert state.stdout.strip() == NOT_BUILT
    site = subprocess.run([str(python), "-c", "import rlbridge; print(rlbridge.__file__)"],
                          capture_output=True, text=True, timeout=60, check=True, cwd=tmp_path)
    package = Path(site.stdout.strip()).parent
    assert (package / "server" / "bindings.py").exists()
    assert list(package.parent.glob("rlbridge*.so")) == []
    assert list(package.rglob("*.so")) == []

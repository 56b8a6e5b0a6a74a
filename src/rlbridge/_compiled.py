"""The value path compiled by mypyc, and whether this process runs it compiled.

``pip install .`` and ``pip install -e .`` compile the modules in :data:`MODULES` (the
per-value code of the server and the SDK's I/O threads) with mypyc when they can (setup.py);
the same modules stay importable as the plain ``.py`` files beside them, so the package works
the same without a compiler. Compiling was measured to pay (docs/benchmarks.md, "Compiled
value path").

The compiled modules call each other directly, so they run all compiled or all as Python: this
module decides which, once, when ``rlbridge`` is imported. They run as Python when

* none was built for this interpreter (``RLBRIDGE_PURE_PYTHON=1`` at install, or no compiler);
* ``RLBRIDGE_PURE_PYTHON`` is set (not ``0``) in the environment now;
* one is missing, or a source changed since the build (an editable checkout edited after
  ``pip install -e .``: the build recorded each source's SHA-256 in ``_compiled_sources.json``),
  so an edit is never shadowed by a stale extension. That last case is the one nobody asked
  for, so it says so: one warning on the ``rlbridge`` logger at import, naming the first
  edited module and the command that compiles again (:func:`edited_notice`). A log record,
  not a :mod:`warnings` warning: a test run with ``-W error`` in an edited checkout should
  still run, only slower.

To run them as Python, a finder placed first on ``sys.meta_path`` loads these modules from
their ``.py`` files: process-wide by nature, like the import system it steers; it is installed
at most once and touches no other module. :data:`STATE` says what was decided
(``rlbridge --version`` prints it). Standard library only: setup.py reads :data:`MODULES` and
:data:`PURE_ENV` from this file before anything is installed.
"""

from __future__ import annotations

import hashlib
import importlib.abc
import importlib.machinery
import importlib.util
import json
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import ModuleType

#: Set (to anything but ``0``) at install: do not compile; at run time: run the Python files.
PURE_ENV = "RLBRIDGE_PURE_PYTHON"
#: The modules setup.py compiles: those a value runs through, per value or per tick.
MODULES: tuple[str, ...] = (
    # server: datagram in -> session -> publish binding -> in-process bus -> subscribe
    # binding -> UDP sink
    "rlbridge.server.udp",
    "rlbridge.server.session",
    "rlbridge.server.values_in",
    "rlbridge.server.bindings",
    "rlbridge.server.sinks",
    "rlbridge.adapters.inproc",
    # SDK: write -> ring -> send round (send thread, or inline) -> datagram; datagram ->
    # receive thread -> ring -> read
    "rlbridge.csp.ring",
    "rlbridge.csp.stamped_ring",
    "rlbridge.csp.channel",
    "rlbridge.client.channels.incoming",
    "rlbridge.client.channels.outgoing",
    "rlbridge.client.session.plain_round",
    "rlbridge.csp.bell",
    "rlbridge.client.session.sender",
    "rlbridge.client.session.receiver",
    # both: the codec, bundles, sequence numbers and clocks
    "rlbridge.wire.codec",
    "rlbridge.wire.bundle",
    "rlbridge.wire.sequence",
    "rlbridge.wire.clock",
    "rlbridge.wire.seal",
)
#: What setup.py records next to the compiled modules: ``{module: sha256 of its source}``.
SOURCES_FILE = "_compiled_sources.json"
#: The command that compiles the value path again (run in the checkout).
REBUILD = "pip install -e ."

_PACKAGE_DIR = Path(__file__).resolve().parent
#: :func:`decide`'s answer when no module was compiled for this interpreter.
NOT_BUILT = "pure Python (not compiled for this interpreter)"


def source_of(module: str, package_dir: Path = _PACKAGE_DIR) -> Path:
    """The ``.py`` file of ``module`` (one of :data:`MODULES`) under ``package_dir``."""
    return package_dir.joinpath(*module.split(".")[1:]).with_suffix(".py")


def digest(path: Path) -> str:
    """SHA-256 of a file's bytes, hex."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def pure_requested(environ: Mapping[str, str]) -> bool:
    """``RLBRIDGE_PURE_PYTHON`` is set to something other than empty or ``0``."""
    return environ.get(PURE_ENV, "") not in ("", "0")


def _extension_of(source: Path, suffixes: Sequence[str]) -> Path | None:
    for suffix in suffixes:
        candidate = source.with_name(source.stem + suffix)
        if candidate.exists():
            return candidate
    return None


def decide(package_dir: Path, environ: Mapping[str, str],
           suffixes: Sequence[str] = tuple(importlib.machinery.EXTENSION_SUFFIXES),
           modules: Sequence[str] = MODULES) -> tuple[bool, str]:
    """(run compiled?, why) for the package in ``package_dir``: see the module docstring."""
    built = [m for m in modules if _extension_of(source_of(m, package_dir), suffixes)]
    if not built:
        return False, NOT_BUILT
    if pure_requested(environ):
        return False, f"pure Python ({PURE_ENV} is set)"
    if len(built) < len(modules):
        return False, (f"pure Python ({len(modules) - len(built)} of the {len(modules)} "
                       "compiled modules are missing)")
    changed = edited(package_dir, modules)
    if changed:
        return False, (f"pure Python ({len(changed)} source(s) changed since they were "
                       f"compiled, e.g. {changed[0]}: {REBUILD} compiles them again)")
    return True, f"compiled (mypyc, {len(modules)} modules)"


def edited(package_dir: Path, modules: Sequence[str] = MODULES) -> list[str]:
    """The modules whose source is not what setup.py compiled (all, with no record)."""
    try:
        recorded = json.loads((package_dir / SOURCES_FILE).read_text())
    except (OSError, ValueError):
        recorded = {}
    return [m for m in modules if recorded.get(m) != digest(source_of(m, package_dir))]


def edited_notice(package_dir: Path, changed: Sequence[str]) -> str:
    """The one warning of an edited checkout: what runs, the first edit, how to compile."""
    root = package_dir.parent.parent  # src/rlbridge -> the checkout
    where = f" in {root}" if (root / "setup.py").exists() else ""
    more = f" (and {len(changed) - 1} more)" if len(changed) > 1 else ""
    return (f"{changed[0]}{more} was edited since it was compiled, so the value path runs as "
            f"pure Python (slower); `{REBUILD}`{where} compiles it again")


class _PythonFiles(importlib.abc.MetaPathFinder):
    """Loads :data:`MODULES` from their ``.py`` files, never their compiled extensions."""

    def __init__(self, package_dir: Path, modules: Sequence[str]) -> None:
        self._package_dir = package_dir
        self._modules = frozenset(modules)

    def find_spec(self, fullname: str, path: Sequence[str] | None,
                  target: ModuleType | None = None) -> importlib.machinery.ModuleSpec | None:
        if fullname not in self._modules:
            return None
        return importlib.util.spec_from_file_location(
            fullname, source_of(fullname, self._package_dir))


def _select() -> str:
    compiled, why = decide(_PACKAGE_DIR, os.environ)
    installed = any(isinstance(f, _PythonFiles) for f in sys.meta_path)
    if not compiled and why != NOT_BUILT and not installed:
        sys.meta_path.insert(0, _PythonFiles(_PACKAGE_DIR, MODULES))
        if REBUILD in why:  # sources edited since the build (decide's last reason)
            import logging  # only here: it imports threading, which rlbridge.wire must not

            logging.getLogger("rlbridge").warning(
                "%s", edited_notice(_PACKAGE_DIR, edited(_PACKAGE_DIR)))
    return why


#: What runs the value path in this process: ``compiled (...)`` or ``pure Python (why)``.
STATE = _select() if __name__ == "rlbridge._compiled" else ""

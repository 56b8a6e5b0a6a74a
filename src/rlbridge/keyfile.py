"""The key file: one format for the server (``--psk-file``) and the SDK (``Psk(file=...)``).

A key is written in hex, everywhere: in this file, in ``$RLBRIDGE_PSK`` and in the SDK's
``Psk(key=...)`` (``openssl rand -hex 32`` makes one). One line per client::

    # name      key (hex) or -     rules (optional)
    robot-7     3f1c...e2          publish=/robot7/*,/cmd_vel subscribe=/robot7/* stats=own
    operator    9a0b...41          stats=all
    camera      -                  publish=/camera/*      # a certificate's name, no key
    *           c4d5...07          publish= subscribe=/status/*

A line ``<hex>`` alone, or ``* <hex>``, is the default key, for any client name without its own
line. ``-`` instead of a key names an identity that proves itself another way (the common name
of its mutual-TLS certificate). The rules: ``publish=`` and ``subscribe=`` are comma-separated
topic globs (``*`` matches any characters, ``/`` included; an empty list allows nothing; no
option at all allows every topic); ``stats=all`` lets the client see every session in
``Stats`` (the default, ``own``, shows it only its own). A client without a proven name (the
default key, or TLS without a client certificate) gets the ``*`` line's rules. ``#`` starts a
comment. The SDK reads the same file and takes the key of its client name, else the default.
"""

from __future__ import annotations

import fnmatch
import os
from dataclasses import dataclass
from pathlib import Path

from rlbridge.wire.auth import parse_key

DEFAULT = "*"
_OPTIONS = ("publish", "subscribe", "stats")


@dataclass(frozen=True)
class Entry:
    """One line: a name (``*`` for the default), its key (None: ``-``) and its rules."""

    name: str
    key: bytes | None
    publish: tuple[str, ...] | None = None
    subscribe: tuple[str, ...] | None = None
    see_all: bool = False

    @property
    def has_rules(self) -> bool:
        return self.publish is not None or self.subscribe is not None or self.see_all

    def allows(self, direction: str, topic: str) -> bool:
        globs = self.publish if direction == "publish" else self.subscribe
        return globs is None or any(fnmatch.fnmatchcase(topic, g) for g in globs)

    def globs(self, direction: str) -> str:
        globs = self.publish if direction == "publish" else self.subscribe
        return "any" if globs is None else ", ".join(globs) or "none"


def parse(text: str, source: str) -> dict[str, Entry]:
    """Every line of a key file by name; ``ValueError`` names the file and line."""
    entries: dict[str, Entry] = {}
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"{source}, line {lineno}"
        words = line.split()
        options = [w for w in words if "=" in w]
        positional = [w for w in words if "=" not in w]
        if words[:len(positional)] != positional or len(positional) not in (1, 2):
            raise ValueError(f"{where}: expected '<hex key>' or '<client-name> <hex key or -> "
                             "[publish=...] [subscribe=...] [stats=all]'")
        name, key_text = (DEFAULT, positional[0]) if len(positional) == 1 else positional
        if name in entries:
            what = "default key" if name == DEFAULT else f"line for client {name!r}"
            raise ValueError(f"{where}: a second {what}")
        key = None if key_text == "-" else parse_key(key_text, where)
        entries[name] = Entry(name, key, *_rules(options, where))
    if not entries:
        raise ValueError(f"{source}: no key in the file")
    return entries


def _rules(options: list[str], where: str
           ) -> tuple[tuple[str, ...] | None, tuple[str, ...] | None, bool]:
    """``(publish, subscribe, see_all)`` from a line's ``name=value`` options."""
    globs: dict[str, tuple[str, ...]] = {}
    see_all: bool | None = None
    for option in options:
        name, _, value = option.partition("=")
        if name not in _OPTIONS or name in globs or (name == "stats" and see_all is not None):
            raise ValueError(f"{where}: unknown or repeated option {name!r} (known: "
                             f"{', '.join(_OPTIONS)})")
        if name == "stats":
            if value not in ("all", "own"):
                raise ValueError(f"{where}: stats= takes 'all' or 'own', not {value!r}")
            see_all = value == "all"
        else:
            globs[name] = tuple(g for g in value.split(",") if g)
    return globs.get("publish"), globs.get("subscribe"), bool(see_all)


def read(path: Path) -> str:
    """The file's text; ``ValueError`` that says which file cannot be read and why."""
    try:
        return path.read_text()
    except OSError as exc:
        raise ValueError(f"cannot read the key file {path}: {exc.strerror}") from None


def key_for(entries: dict[str, Entry], name: str) -> bytes | None:
    """The key ``name`` authenticates with: its own line's, else the default line's."""
    own = entries.get(name)
    if own is not None and own.key is not None:
        return own.key
    default = entries.get(DEFAULT)
    return default.key if default is not None else None


def create(path: Path) -> bool:
    """Write a fresh random default key to ``path`` (mode 600) unless it exists; True if made."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as f:
        f.write("# made by rlbridge; one line per client (docs/security.md)\n"
                f"{os.urandom(32).hex()}\n")
    return True

"""Who may connect: pre-shared keys (from a file or the environment) and client networks.

Keys never come from the command line (they would show in ``ps`` and shell history): the
server reads ``--psk-file`` or, without one, the ``RLBRIDGE_PSK`` environment variable (hex).
The file's format, with the per-client rules that :mod:`rlbridge.server.authz` applies, is
:mod:`rlbridge.keyfile`'s, the same one the SDK reads.
"""

from __future__ import annotations

import ipaddress
import logging
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

from rlbridge import keyfile
from rlbridge.keyfile import Entry
from rlbridge.wire.auth import PSK_ENV, parse_key

log = logging.getLogger("rlbridge.server")

IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network


class KeyStore:
    """The pre-shared keys a server accepts: one default and/or one per client name."""

    def __init__(self, default: bytes | None = None,
                 per_client: Mapping[str, bytes] | None = None) -> None:
        if default is None and not per_client:
            raise ValueError("a key store needs at least one key")
        self._default = default
        self._per_client = dict(per_client or {})

    def key_for(self, name: str) -> bytes | None:
        """The key client ``name`` must prove, or None when no key would let it in."""
        return self._per_client.get(name, self._default)

    def identity(self, name: str) -> str | None:
        """``name``, when a proof for it shows the client holds *that name's* own key."""
        return name if name in self._per_client else None

    @classmethod
    def of(cls, entries: dict[str, Entry]) -> KeyStore | None:
        """The keys among a key file's lines (None if every line is ``-``)."""
        default = entries.get(keyfile.DEFAULT)
        per_client = {n: e.key for n, e in entries.items()
                      if n != keyfile.DEFAULT and e.key is not None}
        key = default.key if default is not None else None
        return cls(key, per_client) if key is not None or per_client else None

    @classmethod
    def parse(cls, text: str, source: str) -> KeyStore:
        store = cls.of(keyfile.parse(text, source))
        if store is None:
            raise ValueError(f"{source}: no key in the file")
        return store

    @classmethod
    def load(cls, path: Path | None, environ: Mapping[str, str] = os.environ
             ) -> KeyStore | None:
        """Keys from ``path``, else from ``$RLBRIDGE_PSK``, else None (no authentication)."""
        return load(path, environ)[0]


def load(path: Path | None, environ: Mapping[str, str] = os.environ
         ) -> tuple[KeyStore | None, dict[str, Entry]]:
    """Keys and rules from ``path``, else a key from ``$RLBRIDGE_PSK``, else neither."""
    if path is not None:
        text = keyfile.read(path)
        try:
            mode = path.stat().st_mode
        except OSError as exc:
            raise ValueError(f"cannot read the key file {path}: {exc.strerror}") from None
        if mode & 0o077:
            log.warning("key file %s is readable by others (mode %o); chmod 600 it",
                        path, mode & 0o777)
        entries = keyfile.parse(text, str(path))
        return KeyStore.of(entries), entries
    env = environ.get(PSK_ENV)
    if env:
        return KeyStore(parse_key(env, f"${PSK_ENV}")), {}
    return None, {}


class AllowList:
    """Client networks allowed to connect; empty means everyone (who reaches the bound host)."""

    def __init__(self, networks: Iterable[str]) -> None:
        self.networks: tuple[IPNetwork, ...] = tuple(
            ipaddress.ip_network(n, strict=False) for n in networks)

    def __bool__(self) -> bool:
        return bool(self.networks)

    def allows(self, host: str) -> bool:
        if not self.networks:
            return True
        try:
            addr = ipaddress.ip_address(host.split("%", 1)[0])
        except ValueError:
            return False
        if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
            addr = addr.ipv4_mapped
        return any(addr in net for net in self.networks)

"""Who may connect: pre-shared keys (from a file or the environment) and client networks.

Keys never come from the command line (they would show in ``ps`` and shell history): the
server reads ``--psk-file`` or, without one, the ``RLBRIDGE_PSK`` environment variable. The
file holds one key per line, in hex; a line ``<client-name> <hex>`` gives that client its own
key, a bare ``<hex>`` line is the key for every other client name. ``#`` starts a comment.
"""

from __future__ import annotations

import ipaddress
import logging
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

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

    @classmethod
    def parse(cls, text: str, source: str) -> KeyStore:
        default: bytes | None = None
        per_client: dict[str, bytes] = {}
        for lineno, raw in enumerate(text.splitlines(), 1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            where = f"{source}, line {lineno}"
            match line.split():
                case [key]:
                    if default is not None:
                        raise ValueError(f"{where}: a second default key")
                    default = parse_key(key, where)
                case [name, key]:
                    if name in per_client:
                        raise ValueError(f"{where}: a second key for client {name!r}")
                    per_client[name] = parse_key(key, where)
                case _:
                    raise ValueError(f"{where}: expected '<hex key>' or '<client-name> <hex key>'")
        if default is None and not per_client:
            raise ValueError(f"{source}: no key in the file")
        return cls(default, per_client)

    @classmethod
    def load(cls, path: Path | None, environ: Mapping[str, str] = os.environ
             ) -> KeyStore | None:
        """Keys from ``path``, else from ``$RLBRIDGE_PSK``, else None (no authentication)."""
        if path is not None:
            try:
                text = path.read_text()
                mode = path.stat().st_mode
            except OSError as exc:
                raise ValueError(f"cannot read the key file {path}: {exc.strerror}") from None
            if mode & 0o077:
                log.warning("key file %s is readable by others (mode %o); chmod 600 it",
                            path, mode & 0o777)
            return cls.parse(text, str(path))
        env = environ.get(PSK_ENV)
        if env:
            return cls(parse_key(env, f"${PSK_ENV}"))
        return None


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

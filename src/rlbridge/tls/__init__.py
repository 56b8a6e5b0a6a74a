"""TLS for the TCP transport: contexts, a sans-IO engine both ends drive, certificates.

The engine (:mod:`rlbridge.tls.engine`) runs TLS over memory buffers, so the sockets stay plain
sockets: the client's receive thread keeps waiting on them in ``select`` (which would not see
plaintext an ``SSLSocket`` holds buffered), and the server keeps its own asyncio protocol,
where a refused handshake is logged and counted with its reason. docs/security.md says when
to use TLS and how to set it up.
"""

from rlbridge.errors import TlsError
from rlbridge.tls.context import (
    ClientTls,
    client_tls,
    fingerprint_of,
    server_context,
)
from rlbridge.tls.engine import TlsEngine

__all__ = ["ClientTls", "TlsEngine", "TlsError", "client_tls", "fingerprint_of",
           "server_context"]

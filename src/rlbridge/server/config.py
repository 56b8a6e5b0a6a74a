"""Server configuration: one validated object that the CLI and the Python API both build."""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from rlbridge.wire.codec import DEFAULT_MAX_PACKET, MAX_DATAGRAM

#: The server's UDP receive buffer by default: while the loop is busy or not scheduled, every
#: client's datagrams wait here; 32 MiB (64 as the kernel counts) hold ~80,000 bundles of ten
#: values, 8 s of the load target (100 clients x 100 bundles/s): a stall that long is late
#: values, not lost ones (docs/load.md). A limit, not an allocation.
UDP_RECEIVE_BUFFER = 32 << 20


class ServerConfig(BaseModel):
    """Everything ``Server`` needs; defaults are safe (loopback, both transports, Nagle on)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    host: str = Field("127.0.0.1", description="Address to bind; 0.0.0.0 only when asked.")
    port: int = Field(7411, ge=0, le=65535, description="TCP and UDP port (0: pick a free one).")
    tcp: bool = True
    udp: bool = True
    nodelay: bool = Field(False, description="Set TCP_NODELAY on every client socket.")
    adapter: Literal["inproc", "ros2"] = "inproc"
    node_name: str = "rlbridge"
    namespace: str = ""
    heartbeat_ms: int = Field(200, ge=10, le=60_000)
    timeout_ms: int = Field(600, ge=20, le=600_000)
    max_sessions: int = Field(256, ge=1)
    max_channels: int = Field(256, ge=1, description="Channels per session.")
    max_packet: int = Field(DEFAULT_MAX_PACKET, ge=1024, le=64 << 20)
    max_batch: int = Field(4096, ge=1, description="Values per batch packet.")
    max_write_buffer: int = Field(
        4 << 20, ge=64 << 10, description="Bytes queued to one TCP client before values drop."
    )
    udp_payload: int = Field(
        1400, ge=256, le=MAX_DATAGRAM, description="Largest UDP datagram the server sends."
    )
    udp_receive_buffer: int | None = Field(
        None, ge=64 << 10, le=1 << 30,
        description="Bytes of queued datagrams the UDP socket may hold; a full buffer drops "
        "(docs/load.md). None: 32 MiB, or what net.core.rmem_max allows without "
        "CAP_NET_ADMIN; a size given here that the kernel caps is warned about.")
    use_uvloop: bool = True
    # -- access and limits (docs/security.md) --
    psk_file: Path | None = Field(
        None, description="Pre-shared keys; without it $RLBRIDGE_PSK, without both no auth.")
    tls_cert: Path | None = Field(
        None, description="TLS certificate (PEM); with tls_key, TCP clients must use TLS 1.3.")
    tls_key: Path | None = Field(None, description="The TLS certificate's private key (PEM).")
    tls_client_ca: Path | None = Field(
        None, description="Mutual TLS: clients need a certificate from this CA; its common "
        "name is the client's identity.")
    insecure: bool = Field(
        False, description="Allow an address other than loopback without TLS or a key "
        "(the server then warns at start).")
    allow: tuple[str, ...] = Field(
        (), description="Client networks allowed in (CIDR or address); empty: any.")
    max_rate: float | None = Field(
        None, gt=0, description="Values per second per session (token bucket); None: no limit.")
    max_topic_length: int = Field(256, ge=1, le=256, description="Characters in a topic name.")

    @field_validator("allow")
    @classmethod
    def _networks(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        for net in value:
            try:
                ipaddress.ip_network(net, strict=False)
            except ValueError:
                raise ValueError(f"{net!r} is not a network (e.g. 192.168.1.0/24, 127.0.0.1)"
                                 ) from None
        return value
    metrics_port: int | None = Field(
        None, ge=0, le=65535,
        description="Serve /metrics, /healthz and /status on this port of metrics_host."
    )
    metrics_host: str = Field(
        "127.0.0.1", description="Address of the metrics endpoint: loopback unless asked, "
        "whatever host is (it names clients and topics to anyone, no key asked).")

    @property
    def loopback(self) -> bool:
        """True when ``host`` is a loopback address (only this machine can connect)."""
        return is_loopback(self.host)

    @model_validator(mode="after")
    def _check(self) -> ServerConfig:
        if not (self.tcp or self.udp):
            raise ValueError("enable at least one transport: tcp or udp")
        if self.timeout_ms <= self.heartbeat_ms:
            raise ValueError("timeout_ms must be longer than heartbeat_ms")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("TLS needs both a certificate and its key (--tls-cert and "
                             "--tls-key)")
        if self.tls_client_ca is not None and self.tls_cert is None:
            raise ValueError("--tls-client-ca needs TLS: add --tls-cert and --tls-key")
        return self


def is_loopback(host: str) -> bool:
    """``localhost`` or a loopback address; any other name or address (0.0.0.0, ::, a LAN
    address, a host name) reaches beyond this machine."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.split("%", 1)[0]).is_loopback
    except ValueError:
        return False

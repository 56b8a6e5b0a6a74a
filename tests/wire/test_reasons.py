"""A reason carries at most REASON_MAX characters, whoever made the packet: a constructor on
either side, or the decoder reading a peer that sent a longer one (cut, not refused).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import msgspec
import pytest
from hypothesis import given
from hypothesis import strategies as st

from rlbridge.wire import (
    ConnectError,
    Disconnect,
    Error,
    GoalResult,
    PacketCodec,
    ServiceReply,
    ServiceResult,
    TopicError,
)
from rlbridge.wire.packets import REASON_MAX, cut_reason

CODEC = PacketCodec()
ELLIPSIS = "\u2026"


@given(st.text(max_size=3 * REASON_MAX))
def test_a_cut_reason_fits_and_keeps_its_head(reason: str) -> None:
    cut = cut_reason(reason)
    assert len(cut) <= REASON_MAX
    if len(reason) <= REASON_MAX:
        assert cut == reason
    else:
        assert cut == reason[: REASON_MAX - 1] + ELLIPSIS


REASONED: list[Callable[[str], Any]] = [
    lambda r: ConnectError(22, r),
    lambda r: TopicError(3, 22, r),
    lambda r: Disconnect(0, r),
    lambda r: Error(2, r, 3),
    lambda r: ServiceResult(1, 42, None, r),
    lambda r: ServiceReply(3, 1, 42, None, r),
    lambda r: GoalResult(3, 0, None, r),
]


@pytest.mark.parametrize("make", REASONED)
def test_every_packet_with_a_reason_cuts_it_where_it_is_made(make: Callable[[str], Any]
                                                             ) -> None:
    long = "x" * (REASON_MAX + 500)
    packet = make(long)
    assert packet.reason == long[: REASON_MAX - 1] + ELLIPSIS
    assert CODEC.decode_body(CODEC.encode_frame(packet)[8:]) == packet
    fits = make("y" * REASON_MAX)
    assert fits.reason == "y" * REASON_MAX


def test_a_peer_s_long_reason_is_cut_on_decode_not_refused() -> None:
    body = msgspec.msgpack.encode([6, 7, 22, "no: " + "z" * 5000])
    packet = CODEC.decode_body(body)
    assert isinstance(packet, TopicError)
    assert (packet.channel, packet.code, len(packet.reason)) == (7, 22, REASON_MAX)
    assert packet.reason.startswith("no: zzz")
    assert packet.reason.endswith(ELLIPSIS)

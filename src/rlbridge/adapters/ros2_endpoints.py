"""The ROS 2 adapter's endpoints: a run-time-bound publisher and a batching subscription.

* ``publish`` runs on the caller's thread (the server's event loop). It encodes the whole batch
  first (a bad value publishes nothing), then hands each message to rmw, which copies it into
  the DDS writer's history and returns; rclpy's ``Publisher.publish`` is thread-safe. With
  ``KEEP_LAST`` history a slow or stalled reader never blocks the writer: old samples are
  overwritten (see ``docs/ros2.md`` for measurements).
* Subscription callbacks run on the executor thread. Each callback drains what else is already
  queued on that subscription (``take_message`` until empty, bounded), so a burst costs one
  executor wake-up and one adapter callback with a batch, in order, instead of one per message
  (the thesis's "decode a complete packet at the moment it arrives", for the other direction).
  The server hops to its event loop itself.
* Loss in the subscription's own queue (KEEP_LAST: a full queue drops its oldest message) is
  counted exactly, from the sequence numbers rmw gives each message: every publisher numbers
  its messages, so a gap between two messages of one publisher is that many messages lost
  before this subscription took them (``lost``). Counting starts at the first message of
  each publisher (a volatile subscription never sees what came before it matched). An rmw
  that gives no sequence numbers (they are an rmw_fastrtps feature) leaves ``lost`` at 0.
  rclpy before 8 (Jazzy) gives the sequence number but not the publisher's id: there the
  numbers are used while the subscription has exactly one publisher (whose they must be),
  and not while it has several (they cannot be told apart).

Both are created and destroyed by :class:`~rlbridge.adapters.ros2.Ros2Adapter`, which owns the
node; an endpoint's ``close()`` stops it here and asks the adapter to destroy it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from typing import Any, Protocol

from rlbridge.adapters.base import ValuesCallback, ValueSpec
from rlbridge.adapters.ros2_codecs import ChannelCodec
from rlbridge.adapters.ros2_rclpy import (
    InvalidHandle,
    RCLError,
    RclpyPublisher,
    RclpySubscription,
)

#: The key of the messages that carry no publisher id (rclpy < 8), while one publisher is matched.
ANONYMOUS = b""

# The adapter's logger: one name for everything the ROS 2 adapter logs.
log = logging.getLogger("rlbridge.adapters.ros2")

#: How many already-queued messages one subscription callback takes along in its batch. Bounds
#: the time one busy topic holds the executor thread, so other subscriptions still get a turn.
MAX_BATCH = 1000


class EndpointOwner(Protocol):
    """Who destroys a closed endpoint: the adapter that created it (and owns the node).

    A Protocol, so this module needs no import of :mod:`.ros2` (which imports this one).
    """

    def release_publisher(self, pub: Ros2Publisher) -> None: ...

    def release_subscription(self, sub: Ros2Subscription) -> None: ...


class Ros2Publisher:
    """A run-time-bound publisher (the thesis's RTBPublisher) on one ROS 2 topic."""

    def __init__(
        self, adapter: EndpointOwner, topic: str, codec: ChannelCodec, ros: RclpyPublisher[Any]
    ) -> None:
        self.topic = topic
        self.spec: ValueSpec = codec.spec
        self.published = 0
        #: Messages rmw refused to publish ("cannot publish data"); each is logged and counted.
        self.failed = 0
        self._adapter = adapter
        self._encode = codec.encode
        self.ros = ros
        self._closed = False

    def publish(self, values: Sequence[Any]) -> None:
        """Encode every value (raising ``BindingError`` BAD_VALUE before any is sent), publish."""
        if self._closed:
            raise RuntimeError(f"publisher on {self.topic} is closed")
        encode = self._encode
        messages = [encode(v) for v in values]
        # The rclpy Publisher's own publish() enters the handle and type-checks per message;
        # the messages here are of the publisher's class by construction, so enter once per
        # batch (which also keeps a concurrent close() from destroying it mid-batch) and call
        # the handle directly: about a quarter less per message.
        handle = self.ros.handle
        sent = 0
        try:
            with handle:
                for msg in messages:
                    try:
                        handle.publish(msg)
                    except RCLError as exc:
                        # rmw refused this one message (Fast DDS in ASYNCHRONOUS mode does so
                        # when its history is full of unsent samples): a middleware condition,
                        # not the client's fault. Count it, keep the session and the batch.
                        self.failed += 1
                        if self.failed == 1 or self.failed % 1000 == 0:
                            reason = str(exc).split(", at /", 1)[0]
                            log.warning("ros2 publisher on %s: %s (%d messages refused so far)",
                                        self.topic, reason, self.failed)
                    else:
                        sent += 1
        except InvalidHandle:
            raise RuntimeError(f"publisher on {self.topic} is closed") from None
        finally:
            self.published += sent

    def stop(self) -> bool:
        """Refuse further publishes; ``True`` if it was open (the adapter then destroys it)."""
        was_open, self._closed = not self._closed, True
        return was_open

    def close(self) -> None:
        if self.stop():
            self._adapter.release_publisher(self)


class Ros2Subscription:
    """A topic listener: ROS 2 messages to the adapter callback, in batches, until closed."""

    def __init__(
        self, adapter: EndpointOwner, topic: str, codec: ChannelCodec, callback: ValuesCallback
    ) -> None:
        self.topic = topic
        self.spec: ValueSpec = codec.spec
        #: Values handed to the callback, callbacks made, and callbacks that raised.
        self.delivered = 0
        self.batches = 0
        self.errors = 0
        #: Messages lost before this subscription took them (sequence gaps; module doc), and
        #: messages it took but could not deliver (a batch that failed to decode or deliver).
        self.lost = 0
        self._last_seq: dict[bytes, int] = {}
        #: rclpy < 8: matched publishers when last looked (once per batch; -1: not yet).
        self._publishers = -1
        self._looked = False
        self._adapter = adapter
        self._msg_cls = codec.msg_cls
        self._decode = codec.decode
        self._callback = callback
        # Held while the callback runs; close() takes it, so once close() returns the callback
        # is not running and will not run again.
        self._lock = threading.RLock()
        self._closed = False
        self.ros: RclpySubscription[Any] | None = None  # set by the adapter right after

    def on_message(self, msg: Any, info: Any) -> None:
        """Executor thread: take whatever is queued behind ``msg``, decode, deliver once.

        Two parameters, so rclpy passes the message info (sequence numbers) too. Messages
        taken from ROS and then not delivered (a decode error, a failing callback) are
        counted in ``lost`` as well: the server took them from ROS and could not hand them on.
        """
        taken = [msg]
        self._looked = False
        try:
            self._count_gap(info)
            self._drain(taken)
            decode = self._decode
            batch = [decode(m) for m in taken]
            with self._lock:
                if self._closed:
                    return
                self._callback(batch)
                self.delivered += len(batch)
                self.batches += 1
        except Exception:
            # The executor thread is shared by every subscription: one failing callback must
            # not stop delivery to the others, so log it with its traceback and count it.
            self.errors += 1
            self.lost += len(taken)
            log.exception("ros2 subscription on %s: delivering a batch of %d failed",
                          self.topic, len(taken))

    def _drain(self, taken: list[Any]) -> None:
        """Take the messages already queued behind the first (at most ``MAX_BATCH`` in all)."""
        ros = self.ros
        if ros is None:
            return
        cls, handle = self._msg_cls, ros.handle
        try:
            with handle:
                while len(taken) < MAX_BATCH:
                    message: tuple[Any, Any] | None = handle.take_message(cls, False)
                    if message is None:
                        return
                    self._count_gap(message[1])
                    taken.append(message[0])
        except InvalidHandle:  # destroyed by close() on another thread: deliver what we have
            return

    def _count_gap(self, info: Any) -> None:
        """Count the messages of this message's publisher that never reached us."""
        try:
            seq = info["publication_sequence_number"]
            publisher = info.get("publisher_gid")
        except (KeyError, TypeError, AttributeError):
            return
        if seq is None:
            return
        gid = self._anonymous() if publisher is None else publisher["data"]
        if gid is None:
            return
        last = self._last_seq.get(gid)
        if last is not None and seq > last + 1:
            self.lost += seq - last - 1
        if last is None or seq > last:
            self._last_seq[gid] = seq

    def _anonymous(self) -> bytes | None:
        """rclpy < 8 (no publisher id): the key to count under, if one publisher is matched.

        Looked up once per batch. When the number of publishers changes, the numbers seen so
        far may be another publisher's: counting starts again at the next message.
        """
        if not self._looked:
            self._looked = True
            ros = self.ros
            try:
                count = ros.get_publisher_count() if ros is not None else 0
            except (InvalidHandle, RCLError):
                count = 0
            if count != self._publishers:
                self._publishers = count
                self._last_seq.pop(ANONYMOUS, None)
        return ANONYMOUS if self._publishers == 1 else None

    def stop(self) -> bool:
        """Stop delivering (waits for a running callback); ``True`` if it was open."""
        with self._lock:
            was_open, self._closed = not self._closed, True
        return was_open

    def close(self) -> None:
        if self.stop():
            self._adapter.release_subscription(self)

"""The HRT loop in its own OS process: values cross in shared memory (docs/gil.md).

Why: in one interpreter the loop shares the GIL with the SDK's receive and send threads and
with any Python code the application runs next to it; a thread that holds the GIL when the
loop's timer expires delays the release (docs/gil.md measures by how much). A loop in its own
process has its interpreter to itself, and the only thing it shares with the SDK process is
a block of memory that neither side locks.

Theory of operation. One :class:`ShmLink` segment (``multiprocessing.shared_memory``) holds

* ``inputs`` **latest-value slots** (SDK process -> loop), one ``float64`` each, behind a
  seqlock: the writer makes the sequence word odd, stores the value, makes it even again; the
  reader takes the value only if it saw the same even sequence before and after. The loop
  never waits: after a few torn attempts it keeps the value it had (counted in
  ``torn_reads``), which is what a non-blocking channel of size 1 does (thesis figure 5.3).
* ``outputs`` **SPSC rings** (loop -> SDK process) of ``capacity`` ``float64`` values: the
  loop stores the value, then publishes the new head; the SDK process reads up to the head,
  then publishes the new tail. A full ring refuses the value and counts it in ``dropped``
  (a shared counter only the loop writes), so a slow pump loses values visibly, never the
  loop's timing.
* a **stop word** the owner sets to ask the loop process to end, and a **release counter**
  the loop bumps every cycle, so the SDK process can watch it run.

Every access is one aligned 8-byte load or store of a ``memoryview`` item: no lock, no system
call, no allocation except the ``float`` object a read returns. Correctness rests on those
stores being atomic and seen by the other core in program order, which x86-64 guarantees
(TSO); on a weakly ordered CPU (ARM) a value could be seen before its sequence or head word,
and there is no portable fence from Python, so :meth:`ShmLink.create` refuses to run there.

Lifetime: the process that calls :meth:`ShmLink.create` owns the segment and unlinks it in
:meth:`ShmLink.close` (and, should it die first, CPython's resource tracker unlinks it).
Other processes :meth:`ShmLink.attach` by name and only detach. :class:`HrtProcess` starts
the loop process (``spawn``: nothing inherited but the arguments), asks it to stop through
the stop word, joins it and kills it if it does not end. :func:`forwarder` is the SDK
process's side: copy bridge inputs into the slots and drain the rings into bridge outputs,
run by a lower-priority :class:`~rlbridge.hrt.coupling.Ticker` at the pump rate.
"""

from __future__ import annotations

import multiprocessing
import platform
import signal
from collections.abc import Callable, Sequence
from multiprocessing import resource_tracker, shared_memory
from types import TracebackType
from typing import Any, Final, Protocol

__all__ = ["HrtProcess", "ShmLink", "ShmLinkError", "forwarder"]

_MAGIC: Final = 0x524C42_53484D_01  # "RLB" "SHM" v1
_HEADER: Final = 8  # words: magic, inputs, outputs, capacity, stop, releases, 2 spare
_RING_HEADER: Final = 16  # head and dropped in one cache line, tail in the next
_TORN_RETRIES: Final = 4
_STRONG_ORDERING: Final = frozenset({"x86_64", "amd64", "i386", "i686", "x86"})


_created_here: set[str] = set()
"""Segments this process created and still owns (their resource-tracker entry is the owner's)."""


class ShmLinkError(RuntimeError):
    """The segment is missing, not an rlbridge link, or laid out differently than asked."""


class ShmLink:
    """Latest-value slots in, SPSC rings out, in one shared-memory segment; see module doc.

    Loop side (one thread): :meth:`get`, :meth:`push`, :attr:`stop_requested`,
    :meth:`count_release`.
    SDK side (one thread): :meth:`put`, :meth:`drain`, :meth:`request_stop`.
    """

    def __init__(self, shm: shared_memory.SharedMemory, *, owner: bool) -> None:
        buf = shm.buf
        if buf is None or len(buf) < 8 * _HEADER:
            raise ShmLinkError(f"shared memory {shm.name!r} is too small for a link")
        q = buf.cast("q")
        if q[0] != _MAGIC:
            q.release()
            raise ShmLinkError(f"shared memory {shm.name!r} is not an rlbridge ShmLink")
        self.shm: Final = shm
        self.owner: Final = owner
        self.inputs: Final = int(q[1])
        self.outputs: Final = int(q[2])
        self.capacity: Final = int(q[3])
        self._q = q
        self._d = buf.cast("d")
        self._slots = _HEADER
        self._rings = _HEADER + ((2 * self.inputs + 7) // 8) * 8
        self._latest = [0.0] * self.inputs  # loop side: what get() returns when torn
        self.torn_reads = 0
        self._closed = False

    @staticmethod
    def size(inputs: int, outputs: int, capacity: int) -> int:
        """Bytes of a segment with this layout."""
        slots = ((2 * inputs + 7) // 8) * 8
        return 8 * (_HEADER + slots + outputs * (_RING_HEADER + capacity))

    @staticmethod
    def supported() -> bool:
        """Whether this machine's store ordering lets a link run here (x86 and x86-64)."""
        return platform.machine().lower() in _STRONG_ORDERING

    @classmethod
    def create(cls, inputs: int = 1, outputs: int = 1, capacity: int = 4096,
               *, name: str | None = None) -> ShmLink:
        """A new segment, owned (unlinked on :meth:`close`) by the calling process."""
        if not cls.supported():
            machine = platform.machine().lower()
            raise ShmLinkError(f"ShmLink relies on x86 store ordering; this is {machine!r} "
                               "(see the rlbridge.hrt.shm module docstring)")
        if inputs < 0 or outputs < 0 or inputs + outputs == 0:
            raise ValueError(f"a link needs inputs or outputs, got {inputs} and {outputs}")
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        shm = shared_memory.SharedMemory(name=name, create=True,
                                         size=cls.size(inputs, outputs, capacity))
        buf = shm.buf
        if buf is None:  # pragma: no cover  only after close()
            raise ShmLinkError(f"shared memory {shm.name!r} is not mapped")
        q = buf.cast("q")  # a fresh segment is zero-filled
        q[1], q[2], q[3] = inputs, outputs, capacity
        q[0] = _MAGIC  # last: an attach that sees the magic sees the layout
        q.release()
        _created_here.add(shm.name)
        return cls(shm, owner=True)

    @classmethod
    def attach(cls, name: str) -> ShmLink:
        """Map an existing segment by name; :meth:`close` only detaches."""
        try:
            shm = shared_memory.SharedMemory(name=name)
        except FileNotFoundError:
            raise ShmLinkError(f"no shared memory named {name!r} (has its owner closed it?)"
                               ) from None
        try:
            link = cls(shm, owner=False)
        except ShmLinkError:
            shm.close()
            raise
        if multiprocessing.parent_process() is None and name not in _created_here:
            # A process not started by multiprocessing (nor the owner itself) has its own
            # resource tracker, which would unlink the owner's segment when this process
            # exits. (SharedMemory(track=False) is 3.13+.)
            resource_tracker.unregister(shm._name, "shared_memory")  # type: ignore[attr-defined]
        return link

    @property
    def closed(self) -> bool:
        """This process has detached (after :meth:`close`, nothing else may be called)."""
        return self._closed

    @property
    def name(self) -> str:
        """What another process passes to :meth:`attach`."""
        return self.shm.name

    # -- SDK side ------------------------------------------------------------------------------

    def put(self, slot: int, value: float) -> None:
        """Publish the latest value of input ``slot`` (one writer per slot)."""
        q, at = self._q, self._slots + 2 * self._check(slot, self.inputs)
        seq = q[at]
        q[at] = seq + 1
        self._d[at + 1] = value
        q[at] = seq + 2

    def drain(self, ring: int, max_items: int | None = None) -> list[float]:
        """Take what the loop pushed to output ``ring``, oldest first (one reader per ring)."""
        q, d, cap = self._q, self._d, self.capacity
        at = self._ring_at(ring)
        head, tail = q[at], q[at + 8]
        if max_items is not None:
            head = min(head, tail + max_items)
        data = at + _RING_HEADER
        values = [d[data + i % cap] for i in range(tail, head)]
        q[at + 8] = head
        return values

    def dropped(self, ring: int) -> int:
        """Values the loop could not push to ``ring`` because it was full."""
        return int(self._q[self._ring_at(ring) + 1])

    def request_stop(self) -> None:
        """Ask the loop process to end (it reads :attr:`stop_requested` each cycle)."""
        self._q[4] = 1

    # -- loop side -----------------------------------------------------------------------------

    def get(self, slot: int) -> float:
        """The latest value of input ``slot`` (0.0 before the first put); never waits."""
        q, d, at = self._q, self._d, self._slots + 2 * self._check(slot, self.inputs)
        for _ in range(_TORN_RETRIES):
            before = q[at]
            value = d[at + 1]
            if not before & 1 and q[at] == before:
                self._latest[slot] = value
                return value
        self.torn_reads += 1
        return self._latest[slot]

    def push(self, ring: int, value: float) -> bool:
        """Append to output ``ring``; ``False`` (and counted) when it is full."""
        q, at = self._q, self._ring_at(ring)
        head = q[at]
        if head - q[at + 8] >= self.capacity:
            q[at + 1] += 1
            return False
        self._d[at + _RING_HEADER + head % self.capacity] = value
        q[at] = head + 1  # publish after the value is stored
        return True

    @property
    def stop_requested(self) -> bool:
        """The owner asked the loop to end."""
        return bool(self._q[4])

    def count_release(self) -> None:
        """Count one release of the loop (one 8-byte store), so the SDK side sees progress."""
        self._q[5] += 1

    @property
    def releases(self) -> int:
        """Releases the loop has counted with :meth:`count_release` (any side may read)."""
        return int(self._q[5])

    # -- lifetime ------------------------------------------------------------------------------

    def close(self) -> None:
        """Detach (idempotent); the owner also unlinks the segment."""
        if self._closed:
            return
        self._closed = True
        self._q.release()
        self._d.release()
        self.shm.close()
        if self.owner:
            _created_here.discard(self.shm.name)
            self.shm.unlink()

    def __enter__(self) -> ShmLink:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def _ring_at(self, ring: int) -> int:
        return self._rings + self._check(ring, self.outputs) * (_RING_HEADER + self.capacity)

    @staticmethod
    def _check(index: int, count: int) -> int:
        if not 0 <= index < count:
            raise IndexError(f"index {index} out of range for {count}")
        return index

    def __repr__(self) -> str:
        return (f"<ShmLink {self.name!r} inputs={self.inputs} outputs={self.outputs} "
                f"capacity={self.capacity}{' owner' if self.owner else ''}>")


def _hrt_main(name: str, target: Callable[..., object], args: tuple[Any, ...]) -> None:
    # Ctrl-C reaches every process of the terminal's group, this one too. Its owner stops it
    # (``link.request_stop``, then terminate): a KeyboardInterrupt here would only cut the
    # loop short and print a second traceback, the owner's being the one that matters.
    # SIGINT was blocked from before the fork (HrtProcess.start): one that came during the
    # interpreter's start-up is pending, and is dropped here.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    with ShmLink.attach(name) as link:
        target(link, *args)


class HrtProcess:
    """The loop process: ``target(link, *args)`` in a fresh interpreter (``spawn``).

    ``target`` must be importable by name (a module-level function): a spawned process gets
    nothing but its pickled arguments, which is the point. It should loop until
    ``link.stop_requested`` or its own end. The caller keeps owning ``link``.
    """

    def __init__(self, link: ShmLink, target: Callable[..., object], *args: Any,
                 name: str = "rlbridge-hrt") -> None:
        context = multiprocessing.get_context("spawn")
        self.link = link
        self._proc = context.Process(target=_hrt_main, args=(link.name, target, args),
                                     name=name, daemon=True)

    def start(self) -> None:
        """Start the loop's process (its own interpreter: no GIL shared with the SDK).

        SIGINT is blocked in this thread while it forks: the child inherits the mask through
        exec, so a Ctrl-C during its start-up cannot kill its interpreter half-way ("Fatal
        Python error: init_import_site"); here a blocked Ctrl-C is delayed, never lost.
        """
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            self._proc.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)

    @property
    def sentinel(self) -> int:
        """Ready when the process ends (for ``multiprocessing.connection.wait``)."""
        return self._proc.sentinel

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the loop process; ``False`` if it is still running after ``timeout``."""
        self._proc.join(timeout)
        return self._proc.exitcode is not None

    @property
    def exitcode(self) -> int | None:
        """The loop process's exit status, ``None`` while it runs: a crashed loop shows here."""
        return self._proc.exitcode

    def stop(self, timeout: float = 5.0) -> int | None:
        """Ask it to stop, wait ``timeout``, then terminate (and kill); return the exit code.

        Idempotent, and a no-op for a process that was never started.
        """
        if self._proc.pid is None:
            return None
        self.link.request_stop()
        if not self.join(timeout):
            self._proc.terminate()
            if not self.join(timeout):
                self._proc.kill()
                self._proc.join()
        return self._proc.exitcode

    def __enter__(self) -> HrtProcess:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()


class _Readable(Protocol):
    def read(self) -> Any: ...


class _Writable(Protocol):
    def write_many(self, values: Sequence[Any]) -> None: ...


def forwarder(link: ShmLink, inputs: Sequence[_Readable],
              outputs: Sequence[_Writable]) -> Callable[[], None]:
    """The SDK process's pump step: ``inputs[i]`` -> slot ``i``, ring ``j`` -> ``outputs[j]``.

    Inputs should be non-blocking channels (the pump must not wait on one topic while the
    others go stale); run the step in a :class:`~rlbridge.hrt.coupling.Ticker` at a rate at
    least ``loop rate / capacity`` so the rings never fill.
    """
    if len(inputs) != link.inputs or len(outputs) != link.outputs:
        raise ValueError(f"{link!r} needs {link.inputs} inputs and {link.outputs} outputs, "
                         f"got {len(inputs)} and {len(outputs)}")
    slots = tuple(enumerate(inputs))
    rings = tuple(enumerate(outputs))

    def step() -> None:
        for slot, source in slots:
            link.put(slot, float(source.read()))
        for ring, sink in rings:
            values = link.drain(ring)
            if values:
                sink.write_many(values)

    return step

"""The demo's roles, end to end: start, watch, stop in order, then report.

``all``
    Both sides in one process (the default of ``rlbridge demo``): a server on the in-process bus
    (or ROS 2), the vision and monitor nodes on it, and the controller connected over loopback
    TCP + UDP. Everything crosses a real server; nothing is shortcut in memory.
``bridge``
    The middleware side only (the resource-rich machine, or the ``bridge`` compose service).
``controller``
    The embedded side only (the board, or the ``controller`` compose service): connects to
    ``--host``, retrying until the server answers.

Each role runs for ``seconds`` (0: until SIGINT/SIGTERM). The controller rides out outages:
its bridge reconnects by itself and the loop resumes tracking. With ``lost_exit`` > 0 it instead
ends once its link has been lost that long, with exit status 3 (the behaviour from before the
SDK could reconnect, for a supervisor that prefers to restart the process).
"""

from __future__ import annotations

import json
import math
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal, TextIO

from rlbridge import Psk, keyfile
from rlbridge.demo.controller import PanTiltController
from rlbridge.demo.dashboard import WINDOW, AnsiDashboard, LineReport, Status, View, states_line
from rlbridge.demo.loop import ControllerState
from rlbridge.demo.metrics import TrackingMetrics, tracking_metrics
from rlbridge.demo.monitor import GONE, Trace, TraceSnapshot
from rlbridge.demo.plot import PlotUnavailable, write_plot
from rlbridge.demo.sides import AdapterName, connect_controller, middleware_side, switch_interval
from rlbridge.demo.topics import DEFAULT_NAMESPACE, Diagnostics, Topics
from rlbridge.demo.vision import Dropout

Role = Literal["all", "bridge", "controller"]
EXIT_LOST_LINK = 3
REFRESH_S = 0.1
SETTLE_S = 0.5


@dataclass(frozen=True)
class DemoOptions:
    """Everything ``rlbridge demo`` can be told; the CLI only fills this in."""

    role: Role = "all"
    seconds: float = 5.0
    host: str = "127.0.0.1"
    port: int = 0
    adapter: AdapterName = "inproc"
    namespace: str = DEFAULT_NAMESPACE
    vision_start: float = 0.5
    dropout: Dropout = field(default_factory=Dropout)
    dashboard: bool = False
    plot: Path | None = None
    plot_required: bool = False
    """False: without matplotlib the plot is skipped with a note (the default path)."""
    report: Path | None = None
    connect_timeout: float = 30.0
    lost_exit: float = 0.0
    """Exit with status 3 after the link was lost this long (s); 0: never, ride it out."""
    psk: Psk | None = None
    """The key, ``Psk(file=...)`` (the CLI's ``--psk-file``): the bridge side makes the file
    if it is missing and serves with it, the controller connects with it. None: the server and
    the controller take ``$RLBRIDGE_PSK`` if set."""

    def key_file(self) -> Path | None:
        """The file of :attr:`psk` (a server reads its keys from a file: ``Psk(key=...)``
        is refused with a ``ValueError`` naming ``psk``)."""
        if self.psk is None:
            return None
        if self.psk.file is None:
            raise ValueError("DemoOptions.psk: the bridge side serves keys from a file: give "
                             "Psk(file=...), not Psk(key=...)")
        return Path(self.psk.file)


@dataclass
class DemoResult:
    """What a role saw; :meth:`as_dict` is the ``--report`` JSON."""

    role: Role
    address: str
    elapsed: float
    reason: Literal["time", "signal", "lost-link"]
    states: list[tuple[float, str]]
    diagnostics: Diagnostics | None
    metrics: TrackingMetrics | None = None
    snapshot: TraceSnapshot | None = None
    plot: Path | None = None

    @property
    def exit_code(self) -> int:
        return EXIT_LOST_LINK if self.reason == "lost-link" else 0

    def as_dict(self) -> dict[str, Any]:
        snap = self.snapshot
        out: dict[str, Any] = {
            "role": self.role,
            "address": self.address,
            "elapsed_s": self.elapsed,
            "reason": self.reason,
            "states": [[t, s] for t, s in self.states],
            "diagnostics": None if self.diagnostics is None else asdict(self.diagnostics),
            "plot": None if self.plot is None else str(self.plot),
        }
        if self.metrics is not None:
            out["tracking"] = {"settle_s": self.metrics.settle,
                               "pan": self.metrics.pan.as_dict(),
                               "tilt": self.metrics.tilt.as_dict()}
        if snap is not None:
            out["setpoints_published"] = snap.setpoints_total
            out["angles_received"] = dict(snap.angles_total)
            out["angles_sent"] = snap.angles_sent  # to this bridge, over its sessions
            out["angles_lost"] = snap.angles_lost
        finite: dict[str, Any] = _finite(out)
        return finite


def run_demo(options: DemoOptions, out: TextIO) -> DemoResult:
    """Run one role to the end, write the plot and report, print the summary."""
    stop = threading.Event()
    with _stop_on_signals(stop):
        if options.role == "controller":
            result = _run_controller(options, stop, out)
        else:
            result = _run_middleware(options, stop, out)
    skipped = ""
    if options.plot is not None and result.snapshot is not None and result.metrics is not None:
        try:
            result.plot = write_plot(result.snapshot, result.metrics, options.plot,
                                     result.diagnostics)
        except PlotUnavailable as exc:
            if options.plot_required:
                raise
            skipped = f"  plot skipped: {exc}"
    if options.report is not None:
        options.report.parent.mkdir(parents=True, exist_ok=True)
        options.report.write_text(json.dumps(result.as_dict(), indent=2) + "\n")
    for line in [*summary(result), *([skipped] if skipped else [])]:
        out.write(line + "\n")
    out.flush()
    return result


# -- the middleware side (roles "all" and "bridge") --------------------------------------------
def _run_middleware(opts: DemoOptions, stop: threading.Event, out: TextIO) -> DemoResult:
    topics = Topics(opts.namespace)
    with ExitStack() as stack:
        key_file = opts.key_file()
        if key_file is not None and keyfile.create(key_file):
            out.write(f"made a new key file {key_file}: give the controller a copy "
                      "(--psk-file)\n")
        mw = stack.enter_context(middleware_side(
            host=opts.host, port=opts.port, adapter=opts.adapter, topics=topics,
            vision_start=opts.vision_start, dropout=opts.dropout, psk_file=key_file))
        address = f"{opts.host}:{mw.port}"
        out.write(f"bridge server on {address} ({opts.adapter}); vision node publishing "
                  f"{topics.setpoint('pan')}, {topics.setpoint('tilt')} at 30 Hz\n")
        controller: PanTiltController | None = None
        if opts.role == "all":
            stack.enter_context(switch_interval(0.0005))
            local = {"0.0.0.0": "127.0.0.1", "::": "::1"}.get(opts.host, opts.host)
            bridge = connect_controller(local, mw.port, timeout=opts.connect_timeout,
                                        stop=stop, security=opts.psk)
            stack.callback(bridge.close)
            controller = PanTiltController(bridge, topics=topics).start()
            stack.callback(controller.close)  # idempotent; runs first on an error
            out.write("controller connected: 1 kHz loop, set-points over UDP, angles sub-sampled "
                      "to 50 Hz, status over TCP\n")
        else:
            out.write("waiting for a controller (rlbridge demo --role controller --host ...)\n")
        out.flush()
        reason = _watch(mw.trace, opts, stop, out, f"rlbridge pan-tilt demo | {address}")
        diag = None
        if controller is not None:
            controller.close()  # final status and diagnostics go out before the bridge closes
            diag = controller.diagnostics()
            final = diag.cycles
            mw.trace.wait_for(lambda s: s.diagnostics is not None
                              and s.diagnostics.cycles == final, timeout=1.0)
        snap = mw.trace.snapshot()
    metrics = tracking_metrics(snap, settle=SETTLE_S)
    return DemoResult(opts.role, address, snap.elapsed, reason, snap.statuses,
                      diag or snap.diagnostics, metrics, snap)


def _watch(trace: Trace, opts: DemoOptions, stop: threading.Event, out: TextIO,
           title: str) -> Literal["time", "signal"]:
    """Refresh the live view until the time is up or a signal arrives."""
    view: View = AnsiDashboard(out) if opts.dashboard else LineReport(out)
    try:
        while not stop.wait(REFRESH_S):
            snap = trace.snapshot(last=WINDOW)
            view.update(Status.of(title, snap, opts.seconds))
            if opts.seconds > 0 and snap.elapsed >= opts.seconds:
                return "time"
        return "signal"
    finally:
        view.close()


# -- the embedded side (role "controller") -----------------------------------------------------
def _run_controller(opts: DemoOptions, stop: threading.Event, out: TextIO) -> DemoResult:
    address = f"{opts.host}:{opts.port}"
    start = time.monotonic()
    with ExitStack() as stack:
        stack.enter_context(switch_interval(0.0005))
        bridge = connect_controller(opts.host, opts.port, timeout=opts.connect_timeout,
                                    stop=stop, security=opts.psk)
        stack.callback(bridge.close)
        out.write(f"controller connected to {address}: 1 kHz loop running\n")
        out.flush()
        controller = PanTiltController(bridge, topics=Topics(opts.namespace)).start()
        stack.callback(controller.close)
        reason = _watch_controller(controller, opts, stop, out)
        controller.close()
        diag = controller.diagnostics()
    states = [(t, s.value) for t, s in controller.states()]
    return DemoResult("controller", address, time.monotonic() - start, reason, states, diag)


def _watch_controller(controller: PanTiltController, opts: DemoOptions, stop: threading.Event,
                      out: TextIO) -> Literal["time", "signal", "lost-link"]:
    start = time.monotonic()
    shown = 0
    next_line = 1.0
    lost_since: float | None = None
    while not stop.wait(REFRESH_S):
        now = time.monotonic() - start
        states = controller.states()
        for t, state in states[shown:]:
            out.write(f"t={t:6.2f}s state -> {state.value}\n")
        shown = len(states)
        if now >= next_line:
            next_line += 1.0
            d = controller.diagnostics()
            out.write(f"t={now:6.2f}s {d.state:<9} link {d.link:<9} set-points "
                      f"{d.setpoints_received} (lost {d.setpoints_lost}, age "
                      f"{d.setpoint_age_ms:.0f} ms) loop p99 {d.late_p99_us / 1e3:.2f} ms "
                      f"missed {d.missed} [{d.scheduling}]\n")
        out.flush()
        if controller.loop.state is not ControllerState.LOST_LINK:
            lost_since = None
        elif opts.lost_exit > 0:
            lost_since = now if lost_since is None else lost_since
            if now - lost_since >= opts.lost_exit:
                return "lost-link"
        if opts.seconds > 0 and now >= opts.seconds:
            return "time"
    return "signal"


# -- reporting ---------------------------------------------------------------------------------
#: Why a role ended, as the summary's tag says it (the report's ``reason`` is the bare word).
REASONS = {"time": "time: --seconds ran out", "signal": "signal: stopped by SIGINT or SIGTERM",
           "lost-link": "lost-link: the link was lost for --lost-exit seconds"}


def summary(result: DemoResult) -> list[str]:
    """The lines printed at the end of every role."""
    lines = [f"pan-tilt demo ({result.role}) finished after {result.elapsed:.1f} s "
             f"[{REASONS[result.reason]}], bridge {result.address}"]
    lines.append(f"  states: {states_line(result.states, limit=8)}")
    m = result.metrics
    if m is not None:
        if m.samples:
            lines.append(f"  tracking error (set-point - angle, {m.samples} samples after "
                         f"{m.settle:g} s settling), mrad:")
            lines.extend(f"    {axis:<4} rms {a.rms * 1e3:5.1f}  median {a.median_abs * 1e3:5.1f}"
                         f"  max {a.max_abs * 1e3:5.1f}"
                         for axis, a in (("pan", m.pan), ("tilt", m.tilt)))
        else:
            lines.append(f"  tracking error: no settled tracking samples ({_why_none(result)})")
    d = result.diagnostics
    if d is not None:
        lines.append(f"  loop: {d.cycles} cycles, lateness p50 {d.late_p50_us / 1e3:.3f} ms, "
                     f"p99 {d.late_p99_us / 1e3:.3f} ms, max {d.late_max_us / 1e3:.3f} ms, "
                     f"missed {d.missed} ({d.scheduling})")
        sent = d.setpoints_received + d.setpoints_lost
        lost = f"  values lost: set-points {d.setpoints_lost} of {sent} (UDP)"
        if result.snapshot is not None:
            snap = result.snapshot
            lost += f", angles {snap.angles_lost} of {snap.angles_sent} (UDP)"
        lines.append(lost)
        last = result.states[-1] if result.states else None
        link = (f"its session closed at {last[0]:.1f} s" if last is not None
                and last[1] == GONE else d.link)
        lines.append(f"  controller link: {link}; controller-side error rms "
                     f"{d.error_rms_mrad[0]:.1f} / {d.error_rms_mrad[1]:.1f} mrad")
    if result.plot is not None:
        lines.append(f"  plot: {result.plot}")
    return lines


def _why_none(result: DemoResult) -> str:
    """Why no tracking sample counted: no controller, or one that tracked too briefly."""
    states = [state for _, state in result.states]
    if not states and result.diagnostics is None:
        return "no controller reported"
    if "tracking" not in states:
        return "the controller never reached tracking"
    settle = result.metrics.settle if result.metrics is not None else SETTLE_S
    return (f"tracking lasted less than the {settle:g} s settling time; run longer "
            "(--seconds)")


def _finite(value: Any) -> Any:
    """NaN and infinities become null: the report stays strict JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


@contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT and SIGTERM set ``stop`` (so the run ends in order and still reports)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, lambda _s, _f: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)

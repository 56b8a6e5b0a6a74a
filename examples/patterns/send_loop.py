"""Thesis figure 5.10: the SDK's own send loop sends the buffered values at a fixed rate.

    rlbridge serve &  rlbridge topic hz /example/output std_msgs/msg/Float64 --duration 5 &
    python examples/patterns/send_loop.py --port 7411 --send-rate 100
"""

from __future__ import annotations

from _common import F64, OUTPUT, parser, run, sine_source

from rlbridge.csp.patterns import send_loop


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--send-rate", type=float, default=100.0, help="SDK send loop rate (Hz)")
    args = p.parse_args()
    control = sine_source(args.period_us)
    run(args, lambda bridge, loop: send_loop(bridge, OUTPUT, F64, control, **loop),
        send_rate_hz=args.send_rate)


if __name__ == "__main__":
    main()

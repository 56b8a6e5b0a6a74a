"""The send patterns of thesis chapter 5: the HRT loop computes a sine and sends it out.

    rlbridge serve &  rlbridge topic hz /example/output std_msgs/msg/Float64 --duration 5 &
    python examples/patterns/send.py buffered --port 7411

Patterns (the first argument):

    buffered   figure 5.5: every value, in order, sent by a lower-priority process
    sampled    figure 5.6: a lower-priority timed process sends the latest value (--rate)
    loop       figure 5.10: the SDK's own send loop sends buffered values (--send-rate)
    naive      for comparison: the loop writes an immediate bridge channel
               (through_buffer=False), whose write wakes the SDK's send thread

The loop runs in its own process by default (``--layout thread``: a thread of this one);
the naive pattern always runs in-process.
"""

from __future__ import annotations

from _common import F64, OUTPUT, Sine, parser, run

from rlbridge import send_buffered, send_loop, send_naive, send_sampled


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("pattern", choices=["buffered", "sampled", "loop", "naive"])
    p.add_argument("--rate", type=float, default=100.0, help="sampled: the sampler's rate (Hz)")
    p.add_argument("--send-rate", type=float, default=100.0, help="loop: SDK send rate (Hz)")
    args = p.parse_args()
    control = Sine(args.period_us)
    if args.pattern == "sampled":
        run(args, lambda bridge, loop: send_sampled(
            bridge, OUTPUT, F64, control, rate_hz=args.rate, layout=args.layout, **loop))
    elif args.pattern == "naive":  # in-process only: it exists to be compared
        run(args, lambda bridge, loop: send_naive(bridge, OUTPUT, F64, control, **loop))
    else:
        recipe = send_buffered if args.pattern == "buffered" else send_loop
        run(args, lambda bridge, loop: recipe(bridge, OUTPUT, F64, control, layout=args.layout,
                                              **loop),
            send_rate_hz=args.send_rate if args.pattern == "loop" else None)


if __name__ == "__main__":
    main()

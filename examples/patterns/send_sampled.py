"""Thesis figure 5.6: a lower-priority timed process sends the latest value at a lower rate.

    rlbridge serve &  rlbridge topic hz /example/output std_msgs/msg/Float64 --duration 5 &
    python examples/patterns/send_sampled.py --port 7411 --rate 50
"""

from __future__ import annotations

from _common import F64, OUTPUT, parser, run, sine_source

from rlbridge.csp.patterns import send_sampled


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--rate", type=float, default=100.0, help="send rate of the sampler (Hz)")
    args = p.parse_args()
    control = sine_source(args.period_us)
    run(args, lambda bridge, loop: send_sampled(bridge, OUTPUT, F64, control,
                                                rate_hz=args.rate, **loop))


if __name__ == "__main__":
    main()

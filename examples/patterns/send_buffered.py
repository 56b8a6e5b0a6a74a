"""Thesis figure 5.5: every value, in order, sent by a lower-priority process.

    rlbridge serve &  rlbridge topic hz /example/output std_msgs/msg/Float64 --duration 5 &
    python examples/patterns/send_buffered.py --port 7411
"""

from __future__ import annotations

from _common import F64, OUTPUT, parser, run, sine_source

from rlbridge.csp.patterns import send_buffered


def main() -> None:
    args = parser(__doc__ or "").parse_args()
    control = sine_source(args.period_us)
    run(args, lambda bridge, loop: send_buffered(bridge, OUTPUT, F64, control, **loop))


if __name__ == "__main__":
    main()

"""For comparison: the HRT loop writes an immediate bridge channel (``through_buffer=False``).

    rlbridge serve &  rlbridge topic hz /example/output std_msgs/msg/Float64 --duration 5 &
    python examples/patterns/send_naive.py --port 7411
"""

from __future__ import annotations

from _common import F64, OUTPUT, parser, run, sine_source

from rlbridge.csp.patterns import send_naive


def main() -> None:
    args = parser(__doc__ or "").parse_args()
    control = sine_source(args.period_us)
    run(args, lambda bridge, loop: send_naive(bridge, OUTPUT, F64, control, **loop))


if __name__ == "__main__":
    main()

"""For comparison: the HRT loop reads a *blocking* bridge channel (do not do this).

The loop runs when a message arrives, not when its timer says: most releases are missed and
the rest are late by up to one period. rlbridge reports it with a RealTimeWarning and the
channel's ``hrt_blocking_reads`` counter.

    rlbridge serve &  python examples/patterns/receive_naive.py --port 7411
"""

from __future__ import annotations

from _common import F64, SETPOINT, ignore, parser, run

from rlbridge import receive_naive


def main() -> None:
    p = parser(__doc__ or "", layouts=False)
    p.add_argument("--no-publish", dest="publish", action="store_false",
                   help="without a publisher the loop blocks in its first read until Ctrl-C")
    args = p.parse_args()
    run(args, lambda bridge, loop: receive_naive(bridge, SETPOINT, F64, ignore, **loop),
        publish=args.publish)


if __name__ == "__main__":
    main()

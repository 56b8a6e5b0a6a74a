"""Thesis figure 5.4: a lower-priority process does the blocking read and feeds the loop.

The helper checks every value (here: clamps it to [-0.5, 0.5]) before the HRT loop sees it;
the loop reads the latest checked value through a non-blocking channel.

    rlbridge serve &  python examples/patterns/receive_blocking.py --port 7411
"""

from __future__ import annotations

from typing import Any

from _common import F64, SETPOINT, parser, run

from rlbridge.csp.patterns import receive_blocking


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--no-publish", dest="publish", action="store_false")
    args = p.parse_args()
    seen: list[float] = []

    def check(value: Any) -> float:  # runs in the lower-priority process
        return max(-0.5, min(0.5, float(value)))

    def control(setpoint: Any) -> None:
        seen.append(float(setpoint))

    run(args, lambda bridge, loop: receive_blocking(bridge, SETPOINT, F64, control,
                                                    process=check, **loop),
        publish=args.publish)
    print(f"  loop saw values in [{min(seen):+.2f}, {max(seen):+.2f}]")


if __name__ == "__main__":
    main()

"""Thesis figure 5.4: a lower-priority process does the blocking read and feeds the loop.

The helper checks every value (here: clamps it to [-0.5, 0.5]) before the HRT loop sees it;
the loop reads the latest checked value without ever waiting. By default the loop runs in its
own process and the helper in this one (``--layout thread``: both threads of this process).

    rlbridge serve &  python examples/patterns/receive_blocking.py --port 7411
"""

from __future__ import annotations

import math
from typing import Any

from _common import F64, SETPOINT, final_law, parser, run

from rlbridge import receive_blocking


def check(value: Any) -> float:
    """Runs in the lower-priority helper, in this process, for every value."""
    return max(-0.5, min(0.5, float(value)))


class Range:
    """The loop's law: remembers the range of what it read."""

    def __init__(self) -> None:
        self.low, self.high = math.inf, -math.inf

    def __call__(self, setpoint: Any) -> None:
        value = float(setpoint)
        self.low, self.high = min(self.low, value), max(self.high, value)


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--no-publish", dest="publish", action="store_false")
    args = p.parse_args()
    control = Range()
    coupling = run(args, lambda bridge, loop: receive_blocking(
        bridge, SETPOINT, F64, control, process=check, layout=args.layout, **loop),
        publish=args.publish)
    seen = final_law(coupling, control)
    print(f"  loop saw values in [{seen.low:+.2f}, {seen.high:+.2f}]")


if __name__ == "__main__":
    main()

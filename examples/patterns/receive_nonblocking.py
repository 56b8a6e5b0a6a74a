"""Thesis figure 5.3: the HRT loop reads a non-blocking bridge channel every cycle.

    rlbridge serve &  python examples/patterns/receive_nonblocking.py --port 7411
"""

from __future__ import annotations

from typing import Any

from _common import F64, SETPOINT, parser, run

from rlbridge.csp.patterns import receive_nonblocking


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--no-publish", dest="publish", action="store_false")
    args = p.parse_args()
    state = {"y": 0.0}

    def control(setpoint: Any) -> None:  # a first-order filter stands in for a controller
        state["y"] += 0.05 * (float(setpoint) - state["y"])

    run(args, lambda bridge, loop: receive_nonblocking(bridge, SETPOINT, F64, control,
                                                       initial=0.0, **loop),
        publish=args.publish)
    print(f"  output after the run: {state['y']:+.3f}")


if __name__ == "__main__":
    main()

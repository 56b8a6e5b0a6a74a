"""Thesis figure 5.3: the HRT loop reads a non-blocking bridge channel every cycle.

By default the loop runs in its own process (``--layout process``) and reads the latest value
from shared memory; ``--layout thread`` runs it as a thread of this process.

    rlbridge serve &  python examples/patterns/receive_nonblocking.py --port 7411
"""

from __future__ import annotations

from typing import Any

from _common import F64, SETPOINT, final_law, parser, run

from rlbridge import receive_nonblocking


class Filter:
    """A first-order filter stands in for a controller (module-level: it can cross)."""

    def __init__(self) -> None:
        self.y = 0.0

    def __call__(self, setpoint: Any) -> None:
        self.y += 0.05 * (float(setpoint) - self.y)


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--no-publish", dest="publish", action="store_false")
    args = p.parse_args()
    control = Filter()
    coupling = run(args, lambda bridge, loop: receive_nonblocking(
        bridge, SETPOINT, F64, control, initial=0.0, layout=args.layout, **loop),
        publish=args.publish)
    print(f"  output after the run: {final_law(coupling, control).y:+.3f}")


if __name__ == "__main__":
    main()

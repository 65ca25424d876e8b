"""``markerpose demo``: the paper's robot experiments on synthetic frames."""

from __future__ import annotations

import time


def cmd_demo(args):
    from ..experiments import demo

    t0 = time.perf_counter()
    demo.main({"seed": args.seed, "alpha": args.alpha}, args.out, progress=not args.quiet)
    print(f"demo finished in {time.perf_counter() - t0:.1f} s")


def register(sub) -> None:
    d = sub.add_parser("demo", help="the paper's robot experiments on synthetic frames; tables vs the paper")
    d.add_argument("--out", default="markerpose-demo", help="output folder (default: markerpose-demo)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--alpha", type=float, default=1.0, help="exposure gain (darkness), default 1")
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    d.set_defaults(func=cmd_demo)

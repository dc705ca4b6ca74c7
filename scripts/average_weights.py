"""Average two detector weights files of one network, tensor by tensor (WiSE-FT's weight-space interpolation:
a fine-tune and the file it started from, mixed, often keep what each does best), as a candidate to score
(docs/detector.md, "What stands in front of the real row"). Its variances are the first file's config only — refit
them with ``jitterguard recalibrate-detector`` before scoring.

    .venv/bin/python scripts/average_weights.py A.pt B.pt OUT.pt [--alpha 0.5]

``alpha`` is B's share (0: A, 1: B). Every floating-point tensor is mixed, the batch-norm running statistics too;
integer ones (the batch counters) are A's. Refuses two files of different networks.
"""

from __future__ import annotations

import argparse
import sys

from jitterguard.services.detector.inference import load_weights, save_weights


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("out")
    ap.add_argument("--alpha", type=float, default=0.5)
    args = ap.parse_args()
    if not 0.0 <= args.alpha <= 1.0:
        ap.error("--alpha must lie in [0, 1]")
    ma, _, _ = load_weights(args.a)
    mb, _, meta_b = load_weights(args.b)
    if ma.config != mb.config:
        sys.exit(f"error: {args.a} and {args.b} are different networks")
    sa, sb = ma.state_dict(), mb.state_dict()
    ma.load_state_dict({k: sa[k] * (1 - args.alpha) + sb[k] * args.alpha if sa[k].is_floating_point() else sa[k]
                        for k in sa})
    save_weights(args.out, ma, meta={"averaged": {"a": args.a, "b": args.b, "alpha": args.alpha},
                                     "source": meta_b.get("source"), "command": " ".join(sys.argv)})
    print(args.out)


if __name__ == "__main__":
    main()

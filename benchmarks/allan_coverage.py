"""How often the Allan read-off's intervals hold the truth (model/allan.py, ``read_noise_terms``).

Simulated still axes: white rate noise of 0.05 deg/s at 200 Hz for 5 min, plus, on a second series,
a rate random walk K of 0.2-5 % of the ARW N per sqrt(s) (just out of the white noise, or not yet).
Prints, over ``--axes`` axes: the ARW's 1-sigma interval's coverage of N; for the walks the curve
shows, K's coverage and the median read / true; for those it does not, the share whose upper bound
``hi`` is above the true K. ``--json`` for the same as JSON.

    python benchmarks/allan_coverage.py [--axes 300] [--seed 7] [--json]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from gyrocal.model.allan import allan_curve, read_noise_terms

RATE_HZ = 200.0
SECONDS = 300.0
NOISE_DPS = 0.05


def run(axes: int, seed: int) -> dict[str, float | int]:
    rng = np.random.default_rng(seed)
    n = int(RATE_HZ * SECONDS)
    n_arw = NOISE_DPS / np.sqrt(RATE_HZ)  # deg/sqrt(s)
    arw_in = k_in = bound_in = 0
    ratios: list[float] = []
    for _ in range(axes):
        y = rng.normal(0.0, NOISE_DPS, n)
        arw = read_noise_terms(allan_curve(y, RATE_HZ)).arw
        arw_in += arw.lo <= n_arw <= arw.hi
        k = n_arw * rng.uniform(0.002, 0.05)  # deg/s/sqrt(s)
        rrw = read_noise_terms(allan_curve(y + np.cumsum(rng.normal(0.0, k / np.sqrt(RATE_HZ), n)),
                                            RATE_HZ)).rate_random_walk
        if rrw.seen:
            ratios.append(rrw.value / k)
            k_in += rrw.lo <= k <= rrw.hi
        else:
            bound_in += k <= rrw.hi
    seen = len(ratios)
    return {"axes": axes, "arw_covered": round(arw_in / axes, 3), "walks_seen": seen,
            "rrw_covered": round(k_in / seen, 3) if seen else float("nan"),
            "rrw_median_read_over_true": round(float(np.median(ratios)), 3) if seen else float("nan"),
            "walks_not_seen": axes - seen,
            "rrw_bound_holds": round(bound_in / (axes - seen), 3) if axes > seen else float("nan")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--axes", type=int, default=300)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--json", action="store_true", help="print JSON")
    args = ap.parse_args()
    out = run(args.axes, args.seed)
    if args.json:
        print(json.dumps(out))
        return
    print(f"ARW interval (1 sigma) holds N on {out['arw_covered']:.1%} of {out['axes']} white axes")
    print(f"walks seen {out['walks_seen']}: K interval holds the truth on {out['rrw_covered']:.1%}, "
          f"median read / true {out['rrw_median_read_over_true']:.2f}")
    print(f"walks not seen {out['walks_not_seen']}: the bound holds on {out['rrw_bound_holds']:.1%}")


if __name__ == "__main__":
    main()

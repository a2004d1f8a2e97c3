"""Does the pose refinement's posterior say how large the error it leaves is? (issue 20.1)

The analytic scans of tests/test_refine.py (laser sheets on a ball and a plate, no renderer,
measurement noise 2 µm along the rays) get arm errors drawn from the prior; the refinement
removes what the crossings see, and its posterior draws (perturb-and-MAP, the ``arm``
contributor of the report's uncertainty) predict the RMS error left along the true normals
(the whole scan's rigid motion taken out, as nothing can see it). Printed per seed: the error
left, the one predicted (RMS over the draws) and their ratio; then the mean ratio per scene
(1 for an honest posterior; above 1: the posterior is too narrow).

    python benchmarks/bench_posterior.py [--seeds 8] [--draws 100]

Writes benchmarks/results/posterior.txt and posterior.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent)]


def main(argv: list[str]) -> int:
    from tests.test_refine import PRIOR, Scan, arm_errors

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--draws", type=int, default=100)
    a = ap.parse_args(argv)
    lines = [f"posterior draws against the error the refinement leaves: analytic scans, arm errors "
             f"from the prior ({PRIOR.sigma_mm * 1e3:.1f} um per axis), {a.draws} draws, µm"]
    out: dict = {"draws": a.draws, "scenes": {}}
    for kind, name in (("sphere", "ball"), ("plane", "plate")):
        s = Scan(kind, noise=0.002)
        ratios = []
        for seed in range(a.seeds):
            _, ref = s.refine(arm_errors(len(s.T), PRIOR, seed=seed), draws=a.draws, seed=seed)
            fpos = np.searchsorted(ref.frames, s.frame)
            left, _ = s.normal_error(ref.points)
            pred = np.sqrt(np.mean([s.normal_error(s.p_true + np.cross(d[fpos, :3], ref.points
                                    - ref.origins[fpos]) + d[fpos, 3:])[0] ** 2
                                    for d in ref.posterior]))
            ratios.append(left / pred)
            lines.append(f"  {name:5s} seed {seed}: left {left * 1e3:.3f}  predicted {pred * 1e3:.3f}"
                         f"  ratio {left / pred:.2f}")
        lines.append(f"  {name:5s} mean ratio left / predicted {np.mean(ratios):.2f} "
                     f"(predicted / left {1 / np.mean(ratios):.2f})")
        out["scenes"][name] = {"ratios": ratios, "mean_ratio": float(np.mean(ratios))}
    text = "\n".join(lines)
    print(text)
    res = HERE / "results"
    (res / "posterior.txt").write_text(text + "\n")
    (res / "posterior.json").write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

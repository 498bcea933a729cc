"""Where iSAM2 weighs the robust factors: their kernel weights at the linearization point and at
the estimate, along a simulated traverse.

    python scripts/robust_weights.py SCENARIO --seed N [--config vo_sites] [--every-m 500]
                                     [--translation-m 0.1] [--kernel huber] [--errors ideal]

GTSAM's Robust model weighs a factor by its residual where iSAM2 linearized it. A stereo tie's
whitened residual moves by several sigma for a centimetre between its pose's and its landmark's
linearization points, and iSAM2 keeps each variable's point until the variable moves by the
relinearization threshold (`--translation-m`, the estimator's relinearize_translation_m). Every
`--every-m` metres this prints the window's robust factors: their mean weight at the
linearization point and at the estimate, and how many differ by more than 0.1.
2026-11-29 (docs/performance.md, "Robust weights at stale linearization points"): short_trail
seed 0, realistic profile, `--every-m 50`: mean weight 0.37 and 0.33 where linearized at 150 and
200 m against 0.985 at the estimate; denver_trail seed 0, `--errors ideal`: 0.55-0.67 against
0.98-0.99.
"""

from __future__ import annotations

import argparse

import numpy as np

from pancam_graph.config import load_scenario, resolve_scenario
from pancam_graph.frontend.motion import motion_between
from pancam_graph.frontend.stereo_vo import StereoVO
from pancam_graph.sim import simulate
from pancam_graph.solve.localizer import Localizer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario")
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--config", default="vo_sites", help="a configuration with sites (vo_sites, vo_sites_hrc)")
    parser.add_argument("--every-m", type=float, default=500.0)
    parser.add_argument("--translation-m", type=float, default=None,
                        help="relinearize_translation_m (default: the scenario's)")
    parser.add_argument("--kernel", default=None, help="the sites' kernel (huber, cauchy; default: the scenario's)")
    parser.add_argument("--errors", default=None, help="error profile (realistic, ideal; default: the scenario's)")
    args = parser.parse_args()
    scenario = load_scenario(resolve_scenario(args.scenario), errors=args.errors)
    estimator = scenario.estimator
    if args.translation_m is not None:
        estimator = estimator.model_copy(update={"relinearize_translation_m": args.translation_m})
    if args.kernel is not None:
        estimator = estimator.model_copy(update={"sites": estimator.sites.model_copy(update={"kernel": args.kernel})})
    traverse, _ = simulate(scenario, args.seed)
    vo = StereoVO.for_traverse(traverse, estimator)
    localizer = Localizer(traverse, estimator.configurations[args.config], estimator, seed=args.seed)
    motion, next_print = None, args.every_m
    print(f"{scenario.name} seed {args.seed}, {args.config}, relinearize_translation_m "
          f"{estimator.relinearize_translation_m:g}, sites' kernel {estimator.sites.kernel}")
    for k, stop in enumerate(traverse.stops):
        if k > 0:
            motion = motion_between(vo, traverse.stops[k - 1], stop, motion, traverse.wheel_slip)
        localizer.step(stop, motion)
        if localizer.smoother.clock_m >= next_print:
            next_print += args.every_m
            weights = localizer.smoother.robust_weights()
            if not weights.at_estimate.size:
                continue
            apart = np.abs(weights.at_linearization - weights.at_estimate) > 0.1
            print(f"{localizer.smoother.clock_m:8.0f} m  {weights.at_estimate.size:5d} robust factors  mean weight "
                  f"{weights.at_linearization.mean():.3f} where linearized, {weights.at_estimate.mean():.3f} at "
                  f"the estimate; {apart.sum()} differ by more than 0.1", flush=True)


if __name__ == "__main__":
    main()

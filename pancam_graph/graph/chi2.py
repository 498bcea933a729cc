"""Chi-square quantiles, the thresholds of every gate and band. From scipy.special (what
scipy.stats.chi2.ppf calls itself): importing scipy.stats takes a second, which every process
of a run would pay at start."""

from __future__ import annotations

from scipy.special import chdtri


def quantile(probability: float, dof: int) -> float:
    """x with P(chi2(dof) <= x) = probability."""
    return float(chdtri(dof, 1.0 - probability))

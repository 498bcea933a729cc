"""Variable keys: X(i) rover body pose at stop i, L(j) landmark with track id j, T(j) rover body
pose at the time of a measurement between two stops (j counts them), S(0) the traverse's wheel
slip."""

from gtsam.symbol_shorthand import L, S, T, X

__all__ = ["L", "S", "T", "X"]

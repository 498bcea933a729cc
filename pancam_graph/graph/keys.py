"""Variable keys: X(i) rover body pose at stop i, L(j) landmark with track id j."""

from gtsam.symbol_shorthand import L, X

__all__ = ["L", "X"]

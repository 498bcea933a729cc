"""Variable keys: X(i) rover body pose at stop i, L(j) landmark with track id j, T(j) rover body
pose at the time of a measurement between two stops (j counts them), S(0) the traverse's wheel
slip, E(k) an error two neighbouring sites' orbital registrations share (a 4-vector)."""

import gtsam
from gtsam.symbol_shorthand import E, L, S, T, X

__all__ = ["E", "L", "S", "T", "X", "subset", "value_type"]

_VALUE_TYPE = {gtsam.Symbol(X(0)).chr(): "Pose3", gtsam.Symbol(T(0)).chr(): "Pose3",
               gtsam.Symbol(L(0)).chr(): "Point3", gtsam.Symbol(S(0)).chr(): "Double",
               gtsam.Symbol(E(0)).chr(): "Vector"}


def value_type(key: int) -> str:
    """The GTSAM type of a kind of variable's values ("Pose3", "Point3", "Double", "Vector")."""
    return _VALUE_TYPE[gtsam.Symbol(key).chr()]


def subset(values: gtsam.Values, keys: list[int]) -> gtsam.Values:
    """The `keys` of `values` (each of the type of its kind of variable)."""
    out = gtsam.Values()
    for key in keys:
        at = getattr(values, f"at{value_type(key)}")
        out.insert(key, at(key))
    return out

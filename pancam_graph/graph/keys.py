"""Variable keys: X(i) rover body pose at stop i, L(j) landmark with track id j, T(j) rover body
pose at the time of a measurement between two stops (j counts them), S(k) a scalar a kind shares
across the traverse (the wheel slip, the VO scale, a map's bias: handed out by `shared`), E(k) an
error two neighbouring sites' orbital registrations share (a 4-vector), C(0) the stereo pair's
calibration error that every site view and VO step shares (a 6-vector, geometry/calibration_error.py)."""

import gtsam
from gtsam.symbol_shorthand import C, E, L, S, T, X

__all__ = ["C", "E", "L", "S", "T", "X", "shared", "shared_blocks", "subset", "value_type"]

_SHARED: dict[str, range] = {}  # owner -> its block of S indices, in the order they were asked for


def shared(owner: str, count: int) -> tuple[int, ...]:
    """The keys of `owner`'s `count` shared scalars S(k): a block of its own, the same at every
    call, after every block handed out before. Kinds take theirs when their module is imported
    (kinds/__init__ imports them in a fixed order), so every process numbers them alike."""
    if count < 1:
        raise ValueError(f"{owner}: a block of shared scalars holds at least one, not {count}")
    block = _SHARED.get(owner)
    if block is None:
        first = max((b.stop for b in _SHARED.values()), default=0)
        block = _SHARED[owner] = range(first, first + count)
    elif len(block) != count:
        raise ValueError(f"{owner} already holds {len(block)} shared scalars, not {count}")
    return tuple(S(k) for k in block)


def shared_blocks() -> dict[str, range]:
    """Every owner's block of S indices (for checks and docs)."""
    return dict(_SHARED)

_VALUE_TYPE = {gtsam.Symbol(X(0)).chr(): "Pose3", gtsam.Symbol(T(0)).chr(): "Pose3",
               gtsam.Symbol(L(0)).chr(): "Point3", gtsam.Symbol(S(0)).chr(): "Double",
               gtsam.Symbol(E(0)).chr(): "Vector", gtsam.Symbol(C(0)).chr(): "Vector"}


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

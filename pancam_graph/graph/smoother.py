"""iSAM2 over a window of the traverse (GTSAM's incremental fixed-lag smoother), with a log of
its updates for batch polishing, the bounds and checkpoints."""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import gtsam
import numpy as np

from ..errors import GraphError
from ..geometry.calibration_error import NAMES as CALIBRATION_TERMS
from .frozen import FrozenRows, row_of, value_of
from .keys import C, E, L, S, T, X
from .update_log import Rebuild, UpdateLog

# The window moves in steps of half its length: each step's update re-eliminates the window,
# and fewer, larger steps keep those costly updates out of a kilometre's 99th percentile
# (docs/performance.md, the window's steps).
WINDOW_STEPS = 2
_POSE_CHR = gtsam.Symbol(X(0)).chr()

# The held linearization point: a Python CustomFactor's error function is handed iSAM2's
# linearization point, and pybind11 copies a `const Values&` it passes to Python unless a Python
# object already wraps that very Values. The copy costs in proportion to the window (a factor's
# linearization took 842 us against 25 us with 5,000 poses in it), on every CustomFactor
# relinearized. Holding iSAM2's own `getLinearizationPoint()` (a reference, not a copy) for as
# long as the smoother lives makes pybind11 pass that object instead. That object keeps iSAM2
# alive: it goes wherever iSAM2 goes (`_new_isam`, `release_solver`).


@dataclass(frozen=True)
class RelinearizeThresholds:
    """How far a variable's estimate may move from its linearization point before iSAM2
    relinearizes it, by kind of variable (keys.py). GPS moves whole stretches of the
    trajectory by centimetres, which the factors hardly depend on: with one threshold of 0.05
    for everything, each fix relinearized hundreds of poses."""

    rotation_rad: float
    translation_m: float
    scalar: float
    calibration: float  # each term of the stereo pair's calibration error, C(0)

    def threshold_map(self) -> gtsam.ISAM2ThresholdMap:
        thresholds = gtsam.ISAM2ThresholdMap()
        pose = np.r_[np.full(3, self.rotation_rad), np.full(3, self.translation_m)]  # GTSAM: rotation first
        for symbol, vector in ((X, pose), (T, pose), (L, np.full(3, self.translation_m)),
                               (S, np.full(1, self.scalar)), (E, np.full(4, self.scalar)),
                               (C, np.full(len(CALIBRATION_TERMS), self.calibration))):  # E, C: keys.py's vector sizes
            thresholds.insert((chr(gtsam.Symbol(symbol(0)).chr()), vector))
        return thresholds


@dataclass(frozen=True)
class RobustWeights:
    """The weight each robust factor of the window gets from its kernel: at iSAM2's linearization
    point (the weight the solve uses: GTSAM's Robust model weighs a factor by its residual where it
    was linearized) and at the current estimate (the weight it deserves). A stereo tie's whitened
    residual moves by several sigma for a centimetre between its pose's and its landmark's
    linearization points, so under a relinearization threshold of 0.1 m the two disagree
    (docs/performance.md, "Robust weights at stale linearization points")."""

    at_linearization: np.ndarray  # (N,)
    at_estimate: np.ndarray  # (N,)


class Smoother:
    """Collect new factors and values, update iSAM2 once, clear: GTSAM's incremental loop.

    Every new pose arrives with a motion factor and every landmark with at least two stereo
    factors, so the graph is always determined. Still, Cholesky declares long VO chains
    without GPS "indeterminate" (denver_trail: at stop 400): the accumulated uncertainty
    (metres) is ~1e6 times the per-step one (millimetres), and forming the Hessian squares
    that ratio past double precision. QR never forms the Hessian. GPS bounds the uncertainty,
    and there Cholesky is a third faster on the waves of relinearization a fix sets off
    (docs/performance.md): configurations with GPS use it, and a smoother whose Cholesky fails
    goes on with QR (iSAM2 rebuilt by replaying its updates, as from a checkpoint).

    The window: GTSAM 4.3's iSAM2 walks its whole Bayes tree on every update (it counts the
    tree's non-zeros), so an update costs in proportion to everything solved so far. A
    variable is marginalized once the rover has driven `window_m` metres past the stop where
    it entered (GTSAM's IncrementalFixedLagSmoother): its estimate is frozen as it
    stands then, and the information it carried stays as a linear factor on its neighbours.
    On a traverse shorter than the window nothing is marginalized and the smoother is plain
    iSAM2.
    """

    def __init__(self, relinearize: RelinearizeThresholds, relinearize_skip: int, window_m: float,
                 wildfire_threshold: float, factorization: str = "QR", partial_check: bool = False):
        """The settings are the estimator configuration's (`configured`): written once, there."""
        self.relinearize = relinearize
        self.partial_check = partial_check
        self.factorization = factorization
        self.relinearize_skip = relinearize_skip
        self.wildfire_threshold = wildfire_threshold
        self.window_m = window_m
        self.isam = self._new_isam()
        # every update's factors, initial values and key clocks: replaying them into a fresh
        # smoother rebuilds exactly this one (a checkpoint's way back: iSAM2 does not pickle)
        self.log = UpdateLog()
        self.clock_m = 0.0  # distance travelled: the window's clock
        self._entered: OrderedDict[int, float] = OrderedDict()  # key in the window -> clock when it entered
        self.shared: set[int] = set()  # variables of the whole traverse (wheel slip, VO scale)
        self._followers: dict[int, list[int]] = {}  # key in the window -> keys that leave with it
        self._leader: dict[int, int] = {}  # and back
        self.frozen = FrozenRows()  # marginalized variables as they stood when they left the window
        # the translation block (body frame, m^2) of each pose variable's (X) marginal covariance
        # as it left, with its frozen estimate (left_position_covariance)
        self._left_covariances = FrozenRows()
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._new_rebuild: dict[int, Rebuild] = {}
        self._new_tracked: list[int] = []  # positions among the new factors whose iSAM2 index is kept
        self._tracked: dict[tuple[int, int], int] = {}  # ticket (update, position) -> iSAM2 factor index
        self._remove: list[int] = []  # iSAM2 factor indices the next update removes
        self._replaced: list[tuple[int, int]] = []  # and their tickets
        # every update's wall time and the variables it relinearized, summed: a step reads what its
        # updates added (a list an update grew with the traverse)
        self.update_ms_sum = 0.0
        self.relinearized_sum = 0

    def _new_isam(self) -> gtsam.IncrementalFixedLagSmoother:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.relinearize.threshold_map())
        params.relinearizeSkip = self.relinearize_skip
        params.enablePartialRelinearizationCheck = self.partial_check
        params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(self.wildfire_threshold))
        params.setFactorization(self.factorization)  # see the class docstring
        # iSAM2 keeps a null slot for every factor it removed (the marginalized ones), growing by
        # doubling: new factors in the empty slots keep its graphs to the window's size
        # (docs/performance.md measures the memory it saves)
        params.findUnusedFactorSlots = True
        isam = gtsam.IncrementalFixedLagSmoother(self.window_m, params)
        self._linearization_point = isam.getLinearizationPoint()  # see the held linearization point, above
        return isam

    def add(self, factor: gtsam.NonlinearFactor, rebuild: Rebuild | None = None,
            tracked: bool = False) -> tuple[int, int] | None:
        """Collect a factor; a Python CustomFactor needs `rebuild`, (function, arguments) that
        make it again, to survive a checkpoint. `tracked`: a factor that may be replaced later
        (`replace`): its ticket is returned."""
        self._in_window(*factor.keys())
        position = self._new_factors.size()
        if isinstance(factor, gtsam.CustomFactor):
            if rebuild is None:
                raise GraphError("a CustomFactor needs its rebuild recipe to be checkpointed")
            self._new_rebuild[position] = rebuild
        self._new_factors.add(factor)
        if not tracked:
            return None
        self._new_tracked.append(position)
        return (self.log.update_count, position)

    def replace(self, ticket: tuple[int, int], factor: gtsam.NonlinearFactor,
                rebuild: Rebuild | None = None) -> tuple[int, int] | None:
        """Take a tracked factor out in the next update and put `factor` in its place."""
        self._remove.append(self._tracked.pop(ticket))
        self._replaced.append(ticket)
        return self.add(factor, rebuild, tracked=True)

    def forget(self, ticket: tuple[int, int]) -> None:
        """A tracked factor that left the window with its variables."""
        self._tracked.pop(ticket, None)

    def insert(self, key: int, value, shared: bool = False, leaves_with: int | None = None) -> None:
        """A new variable and its initial value. `shared`: one that factors all along the traverse
        touch (it never leaves the window); `leaves_with`: a variable in the window that this one
        leaves with (a landmark with the site that anchors it)."""
        if leaves_with is not None and leaves_with not in self._entered:
            raise GraphError(f"{gtsam.Symbol(key).string()} cannot leave the window with "
                             f"{gtsam.Symbol(leaves_with).string()}, which is not in it")
        self._new_values.insert(key, value)
        if shared:
            self.shared.add(key)
        # a leader leaving in the next update cannot take a variable iSAM2 has never had
        elif leaves_with is not None and self._entered[leaves_with] >= self._stamp() - self.window_m:
            self._followers.setdefault(leaves_with, []).append(key)
            self._leader[key] = leaves_with

    def live(self, key: int) -> bool:
        """Whether the variable is in the window (or waiting for the next update)."""
        return key in self._entered or key in self._leader or key in self.shared or self._new_values.exists(key)

    def update(self, context: str = "") -> float:
        """One iSAM2 update with the collected factors; returns its wall time in ms. Variables
        that entered the window's length ago are marginalized in it."""
        stamps, leaving = self._stamps()
        self._freeze(leaving)
        start = time.perf_counter()
        try:
            self._update_and_solve(self._new_factors, self._new_values, stamps, self._remove)
        except (RuntimeError, ValueError) as exc:  # GTSAM's exceptions arrive as either
            if self.factorization != "CHOLESKY":
                raise GraphError(f"iSAM2 update failed {context}: {exc}") from None
            self.factorization = "QR"  # see the class docstring
            self._replay()
            self._freeze(leaving)  # as QR's iSAM2 has them
            try:
                self._update_and_solve(self._new_factors, self._new_values, stamps, self._remove)
            except (RuntimeError, ValueError) as exc:
                raise GraphError(f"iSAM2 update failed {context}: {exc}") from None
        if self._new_tracked:
            indices = self.isam.getISAM2Result().getNewFactorsIndices()
            for position in self._new_tracked:
                self._tracked[(self.log.update_count, position)] = indices[position]
        elapsed = (time.perf_counter() - start) * 1e3
        self.frozen.write_full()  # no replay will freeze these again now
        self._left_covariances.write_full()
        self.log.append(self._new_factors, self._new_values, stamps, self._new_rebuild, self._remove, self._replaced)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._new_rebuild = {}
        self._new_tracked = []
        self._remove, self._replaced = [], []
        self.update_ms_sum += elapsed
        self.relinearized_sum += self.isam.getISAM2Result().getVariablesRelinearized()
        return elapsed

    def _update_and_solve(self, factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float],
                          removed: list[int]) -> None:
        """One iSAM2 update and its back-substitution (as every update, and every replayed one,
        is solved): an indeterminate system fails in either (GTSAM throws from the solve too)."""
        self.isam.update(factors, values, stamps, removed)
        self._back_substitute()

    def _stamp(self) -> float:
        """The clock in steps of half the window: variables leave in batches, one step's
        worth at a time. A marginalizing update costs more than an ordinary one, and more the
        larger the window (GTSAM orders every variable of the window anew for it)."""
        if not np.isfinite(self.window_m):
            return self.clock_m
        step = self.window_m / WINDOW_STEPS
        return step * np.floor(self.clock_m / step)

    def _stamps(self) -> tuple[dict[int, float], list[int]]:
        """The clock of this update's new variables and of the shared ones (which never leave),
        and the variables this update marginalizes (GTSAM's rule: entered more than the window
        before the latest).

        A variable leaves by when it entered, not by when a factor last touched it: a site pose
        that a later tie touches must not outlive the poses around it, or the variables would
        leave the Bayes tree out of its order (GTSAM 4.3's fixed-lag smoother then fails with
        "Asking to remove variables from the variable index that are not unused")."""
        now = self._stamp()
        stamps = dict.fromkeys(self.shared, now)
        for key in self._new_values.keys():
            if key in self._leader:
                stamps[key] = self._entered[self._leader[key]]
            elif key not in self.shared:
                stamps[key] = self._entered[key] = now
        if not np.isfinite(self.window_m):
            return stamps, []
        cutoff = now - self.window_m
        leaving = []
        for key, entered in self._entered.items():
            if entered >= cutoff:
                break
            leaving.append(key)
        for key in list(leaving):
            del self._entered[key]
            for follower in self._followers.pop(key, ()):
                del self._leader[follower]
                leaving.append(follower)
        return stamps, leaving

    def _freeze(self, leaving: list[int]) -> None:
        """The leaving variables' estimates into `frozen`, and the poses' marginal position
        covariances into `left_position_covariance`, while iSAM2 still has them."""
        if not leaving:
            return
        try:
            isam2 = self.isam.getISAM2()
            estimate = isam2.calculateEstimate(leaving)
            for key in leaving:
                self.frozen.put(key, row_of(estimate, key))
                if gtsam.Symbol(key).chr() == _POSE_CHR:  # GTSAM's tangent space: rotation first
                    self._left_covariances.put(key, isam2.marginalCovariance(key)[3:, 3:])
        except RuntimeError as exc:
            raise GraphError(f"iSAM2 estimate of the variables leaving the window failed: {exc}") from None

    def left_position_covariance(self, key: int) -> np.ndarray | None:
        """The 3x3 translation block (body frame, m^2) of a pose's marginal covariance as it left
        the window; None while it is in it."""
        row = self._left_covariances.get(key)
        return None if row is None else np.array(row).reshape(3, 3)

    def left_position_covariances(self, keys: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """(left, (N, 3, 3)): which of the poses left the window, and their
        `left_position_covariance`s (zeros for the others), looked up together."""
        left, rows = self._left_covariances.rows(keys, 9)
        return left, rows.reshape(-1, 3, 3)

    def release_solver(self) -> None:
        """Let iSAM2 (the window's Bayes tree) go once the estimate and covariances are taken:
        the bound's replay (`marginals_at`) builds a window of its own from the update log, and
        would otherwise come on top of every live one. Nothing but `marginals_at` may be asked
        after this."""
        self._linearization_point = None  # it holds iSAM2 alive (see the held linearization point)
        self.isam = None

    # -- checkpoints ---------------------------------------------------------------------------

    def __getstate__(self) -> dict:
        """Everything but the iSAM2 object (the update log rebuilds it). Only between updates."""
        if self._new_factors.size() or self._new_values.size():
            raise GraphError("a smoother with factors not yet updated cannot be checkpointed")
        unpicklable = ("isam", "_linearization_point", "_new_factors", "_new_values")
        return {k: v for k, v in vars(self).items() if k not in unpicklable}

    def __setstate__(self, state: dict) -> None:
        """iSAM2 rebuilt by replaying every update."""
        vars(self).update(state)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._replay()

    def _replay(self) -> None:
        """iSAM2 made anew by replaying every update (the state it had before them)."""
        self.isam = self._new_isam()
        for update in self.log:
            try:
                self._update_and_solve(update.factors, update.values, update.stamps, update.removed)
            except (RuntimeError, ValueError) as exc:
                raise GraphError(f"rebuilding iSAM2 by replaying its updates failed: {exc}") from None

    def _back_substitute(self) -> None:
        """iSAM2's back-substitution, which it runs lazily: at the next estimate asked for, or at
        the next update that checks relinearization. Where it stops (the wildfire threshold)
        depends on when it runs, and what it leaves decides what is relinearized: run after
        every update, it leaves the same state whatever was asked in between, which a replay
        does not repeat (checking every 10 updates, a resumed run differed without this)."""
        self.isam.getISAM2().getDelta()

    def settle(self, iterations: int = 3) -> None:
        """Extra relinearization passes at the end of a traverse (not counted as per-stop updates)."""
        for _ in range(iterations):
            self.isam.update()

    def pose(self, key: int) -> gtsam.Pose3:
        return self._current(key, "Pose3")

    def estimate_double(self, key: int) -> float:
        return float(self._current(key, "Double"))

    def point(self, key: int) -> np.ndarray:
        return self._current(key, "Point3")

    def vector(self, key: int) -> np.ndarray:
        return self._current(key, "Vector")

    def _current(self, key: int, kind: str):
        """A variable's value: its initial value if not yet in iSAM2, its value when it left the
        window if it has, else the current estimate."""
        if self._new_values.exists(key):
            return getattr(self._new_values, f"at{kind}")(key)
        if not self.live(key):  # looked up in the window first: most queries are there
            row = self.frozen.get(key)
            if row is not None:
                return value_of(key, row)
        try:
            return getattr(self.isam, f"calculateEstimate{kind}")(key)
        except RuntimeError as exc:
            raise GraphError(f"iSAM2 estimate of {gtsam.Symbol(key).string()} failed: {exc}") from None

    def _in_window(self, *keys: int) -> None:
        for key in keys:
            if not self.live(key) and key in self.frozen:
                raise GraphError(f"{gtsam.Symbol(key).string()} left the smoother's window: the rover drove "
                                 f"{self.window_m:g} m past where it entered, and it takes no factor and has no "
                                 "marginal any more")

    def marginal_covariance(self, key: int) -> np.ndarray:
        """Marginal covariance of a variable in the window, from the Bayes tree (tangent space;
        for a Pose3, [rotation, translation] in the body frame)."""
        self._in_window(key)
        try:
            return self.isam.getISAM2().marginalCovariance(key)
        except RuntimeError as exc:
            raise GraphError(f"marginal covariance of {gtsam.Symbol(key).string()} failed: {exc}") from None

    def joint_marginal_covariance(self, *keys: int) -> np.ndarray:
        """Joint marginal covariance of variables in the window (blocks in the order given),
        tangent spaces: 12x12 for two poses."""
        self._in_window(*keys)
        try:
            joint = self.isam.getISAM2().jointMarginalCovariance(list(keys))
        except RuntimeError as exc:
            names = ", ".join(gtsam.Symbol(k).string() for k in keys)
            raise GraphError(f"joint marginal covariance of {names} failed: {exc}") from None
        return np.block([[np.atleast_2d(joint.at(a, b)) for b in keys] for a in keys])

    def robust_weights(self) -> RobustWeights:
        """Every robust factor's kernel weight in the window, at the linearization point and at
        the estimate (RobustWeights)."""
        try:
            estimate = self.isam.calculateEstimate()
            graph = self.isam.getFactors()
            at_linearization, at_estimate = [], []
            for i in range(graph.size()):
                factor = graph.at(i)
                model = factor.noiseModel() if isinstance(factor, gtsam.NoiseModelFactor) else None
                if not isinstance(model, gtsam.noiseModel.Robust):
                    continue
                for values, out in ((self._linearization_point, at_linearization), (estimate, at_estimate)):
                    residual = np.linalg.norm(model.noise().whiten(factor.unwhitenedError(values)))
                    out.append(model.robust().weight(residual))
        except RuntimeError as exc:
            raise GraphError(f"robust weights of the window's factors failed: {exc}") from None
        return RobustWeights(np.array(at_linearization), np.array(at_estimate))

    def window_estimate(self) -> gtsam.Values:
        """The window's current estimate, back-substituted in full (the per-stop queries stop
        where the changes fall below iSAM2's wildfire threshold)."""
        try:
            return self.isam.getISAM2().calculateBestEstimate()
        except RuntimeError as exc:
            raise GraphError(f"iSAM2 estimate failed: {exc}") from None

    def estimate(self) -> gtsam.Values:
        """Every variable: the window's current estimate and the marginalized ones as they left
        (the whole traverse's variables in one `gtsam.Values`: for the batch polish; `stacked`
        gives a traverse's poses and points without it)."""
        values = self.window_estimate()
        for key, row in self.frozen.items():
            values.insert(key, value_of(key, row))
        return values

    def stacked(self, values: gtsam.Values, keys: list[int], width: int) -> np.ndarray:
        """(N, width) rows of the variables' values (a pose: its 3x4 [R | t], row by row; a point:
        its three coordinates): from `values` where it has them (the window's estimate, or a
        whole one), else as they left the window."""
        out = np.empty((len(keys), width))
        inside = np.fromiter((values.exists(k) for k in keys), dtype=bool, count=len(keys))
        for j in np.flatnonzero(inside):
            out[j] = row_of(values, keys[j])
        outside = np.flatnonzero(~inside)
        found, rows = self.frozen.rows([keys[j] for j in outside], width)
        if not found.all():
            missing = keys[outside[np.flatnonzero(~found)[0]]]
            raise GraphError(f"no estimate of {gtsam.Symbol(missing).string()}: neither in the window nor left it")
        out[outside] = rows
        return out

    def marginals_at(self, values: Callable[[list[int]], gtsam.Values], keys: list[int]) -> dict[int, np.ndarray]:
        """Marginal covariances (tangent spaces) of `keys` from this smoother's graph linearized
        at `values` (given the keys a step inserts, their values) and never relinearized (the
        bound at the truth), through the same window: a variable that left it has the marginal
        it had as it left, the others the window's at the end. That is the bound for the
        estimate this smoother gives (frozen as it left, which what came after never reached),
        and it holds a window of the traverse in memory, not all of it.

        The updates are replayed one window step at a time: variables leave by steps, so each
        step's first update is where they do. Factorized as this smoother's updates are:
        Cholesky where GPS bounds the graph (faster there), and QR where Cholesky fails (see the
        class docstring)."""
        try:
            return self._marginals_at(values, keys, self.factorization)
        except GraphError:
            if self.factorization == "QR":
                raise
            return self._marginals_at(values, keys, "QR")

    def _marginals_at(self, values: Callable[[list[int]], gtsam.Values], keys: list[int], factorization: str
                      ) -> dict[int, np.ndarray]:
        params = gtsam.ISAM2Params()
        params.setFactorization(factorization)
        params.enableRelinearization = False
        params.findUnusedFactorSlots = True  # as _new_isam's
        isam = gtsam.IncrementalFixedLagSmoother(self.window_m, params)
        linearization_point = isam.getLinearizationPoint()  # see the held linearization point, above
        wanted = set(keys)
        out: dict[int, np.ndarray] = {}
        clock: dict[int, float] = {}  # key in the window -> its stamp
        start = 0
        for factors, inserted, stamps in self._steps():
            now = max(stamps.values(), default=max(clock.values(), default=0.0))
            try:
                leaving = [k for k, stamp in clock.items() if stamp < now - self.window_m]
                for key in leaving:
                    if key in wanted:
                        out[key] = isam.getISAM2().marginalCovariance(key)
                    del clock[key]
                clock.update(stamps)
                isam.update(factors, values(inserted), stamps)
            except (RuntimeError, ValueError) as exc:
                raise GraphError(f"marginals at the given values failed (update log from factor {start}): "
                                 f"{exc}") from None
            start += factors.size()
        try:
            out.update({key: isam.getISAM2().marginalCovariance(key) for key in wanted - out.keys()})
        except RuntimeError as exc:
            raise GraphError(f"marginals at the given values failed: {exc}") from None
        del linearization_point  # held until here
        return out

    def _steps(self) -> Iterator[tuple[gtsam.NonlinearFactorGraph, list[int], dict[int, float]]]:
        """The update log merged into one update per step of the window's clock: (factors, keys
        inserted, stamps)."""
        step = None
        factors, inserted, stamps = gtsam.NonlinearFactorGraph(), [], {}
        for update in self.log.kept():
            # an update may insert only landmarks, stamped with their anchor's (earlier) clock
            now = max([*update.stamps.values(), *([] if step is None else [step])], default=None)
            if now != step and (factors.size() or inserted):
                yield factors, inserted, stamps
                factors, inserted, stamps = gtsam.NonlinearFactorGraph(), [], {}
            step = now
            factors.push_back(update.factors)
            inserted.extend(update.values.keys())
            stamps.update(update.stamps)
        if factors.size() or inserted:
            yield factors, inserted, stamps

    def batch_polish(self, start: gtsam.Values, max_iterations: int = 50) -> gtsam.Values:
        """Levenberg-Marquardt over the whole graph (all of it in memory), started from `start`."""
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        try:
            return gtsam.LevenbergMarquardtOptimizer(self.log.all_factors(), start, params).optimize()
        except RuntimeError as exc:
            raise GraphError(f"batch Levenberg-Marquardt failed: {exc}") from None


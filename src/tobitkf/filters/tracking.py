r"""Multi-target tracker for similar targets that leave an imager's field of view (Miller 2015 §2.2).

Source: Miller (2015) §2.2, (2.8)–(2.17), Table 2.1; our deviations MA-01 to MA-07
(docs/sources/miller2015-ch1-4.md).

N identical-looking points are tracked by N independent Kalman filters (run here as one batch over
targets) with the constant-velocity model (2.8), (2.10)–(2.11):

.. math::

    x_i = [x, \Delta x, y, \Delta y]^T, \quad x_i(k|k-1) = Ax_i(k-1|k-1) + Bu_i(k), \quad y_i = Cx_i + v

Per frame: predict; associate the unordered detections M with the estimates Y by

1. the first map :math:`j(i) = \arg\min_j\|y_i - m_j\|` (not injective);
2. the second map: among the estimates that chose the same :math:`m_j`, only the closest keeps it
   (MA-05; ``second_map="mutual"`` requires mutual nearest neighbours instead);
3. the gate (2.12)–(2.13): keep the pair only if :math:`\|y_i - m_j\| < T_i = T_o + \alpha O_i(k)`,
   O_i the number of consecutive occluded frames before this one (MA-06);

matched targets get the KF update, unmatched ones keep the prediction (2.14); during the warm-up
(MA-04: a fixed number of frames) the association uses each target's previous measurement instead of
its prediction. Occluded-target feedback (2.15)–(2.17): :math:`B = \mathrm{diag}(\mu, 1, \mu, 1)` and, for an
occluded target i, :math:`u_i = \overline{x_n}_{n\ \text{visible}} - x_i` (posteriors and visibility of the
previous frame), which pulls its velocity to the mean velocity of the visible targets.

Deviations from the source (MA-01, MA-02): the printed (2.16) has the opposite sign
(:math:`x_i - \bar x`), averages over all other targets and applies :math:`\epsilon_i = 1` to targets *in*
the frame, which contradicts the prose ("the error between the occluded state and the mean of the
non-occluded states", used "only when i is occluded"). ``feedback="printed"`` keeps the printed form.
Q, R, P_0, T_o, α, μ are not given (MA-03); the defaults are ours.

Time convention: frame 0 initialises the filters from the supplied locations (one-to-one, fixing the
identities); frames 1..T are tracked; output index k-1 holds frame k.

On the shared core (:mod:`tobitkf.filters.core`): the targets are the runs of one batch, the predict is
the shared :func:`~tobitkf.filters.core.time_update` with the feedback input :math:`Bu_i`, and the update
the shared :func:`~tobitkf.filters.core.measurement_update` with :math:`H_0 = C` and only the matched
targets taking part. The covariance recursion does not depend on the detections, only on which
targets are matched: the targets share one covariance (``state.P`` (1, 4, 4)) until a frame misses
one of them, and a predict that starts from the covariance of the previous predict, bit for bit
(the recursion at its floating-point fixed point), reuses its :math:`\bar P`; with every target
matched, it also reuses the gain K and posterior P of the update from that :math:`\bar P` (core's
fixed-gain route, :math:`\hat x = \bar x + K(y - C\bar x)`) when K has at most one nonzero per row
(the decoupled x/y model of the defaults), where that product is rounded exactly as in the full update.
Both reuses hold in every covariance form (``covariance_update``, standard by default as in the source):
in the square-root form the predict reads, and the memo is keyed on, the factor S (``state.S``, shared
(1, 4, 4) like P until a miss) instead of P, and the update memo also keeps the posterior factor.

Online: ``state = tracker.init(initial)``, ``state = tracker.step(state, frame)`` with one frame of
unordered detections (L, 2) per step; ``filter(detections, initial=...)`` is the loop
over the same step (one frame per row).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np

from .._linalg import psd_sqrt
from .._validation import (
    ShapeError,
    ValidationError,
    as_float,
    as_float_array,
    check_bool,
    check_finite,
    check_int,
    check_option,
    check_psd,
)
from .core import (
    COVARIANCE_FORMS,
    Estimator,
    FilterResult,
    FilterState,
    MeasurementPrediction,
    Transition,
    entering_state,
    mark_trusted,
    measurement_update,
    step_state,
    time_update,
)
from .registry import family_entry, register

__all__ = ["MultiTargetTracker", "TrackResult", "constant_velocity_pixel_model"]

#: up to this many target-detection pairs the distances are computed in Python floats
_FEW_PAIRS = 24


def _constant(M: np.ndarray) -> np.ndarray:
    """A private read-only float copy of a model matrix."""
    c = np.array(M, dtype=float)
    c.setflags(write=False)
    return c


def _cholesky_signs(S: np.ndarray | None) -> np.ndarray | None:
    """The lower-triangular factor ``S`` (..., n, n) of a QR array form with its columns negated where
    the diagonal is negative: the Cholesky factor (diagonal >= 0) of the same :math:`P = SS^T`, bit for
    bit (a negation is exact). Householder QR fixes the factor only up to column signs, and those
    alternate from frame to frame; with the signs fixed the factor reaches the floating-point fixed point
    of the recursion, as P does, so the predict memo applies."""
    if S is None:
        return None
    d = np.diagonal(S, axis1=-2, axis2=-1)
    if not (d < 0).any():
        return S
    return S * np.where(d < 0, -1.0, 1.0)[..., None, :]


def constant_velocity_pixel_model() -> tuple[np.ndarray, np.ndarray]:
    """A (4, 4) and C (2, 4) of (2.10)–(2.11): per-frame constant velocity in pixels."""
    A = np.kron(np.eye(2), [[1.0, 1.0], [0.0, 1.0]])
    C = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    return A, C


@dataclass(frozen=True)
class TrackResult:
    """``mean`` (T, N, 4) posteriors, ``cov`` (T, N, 4, 4), ``assignment`` (T, N) index of the matched detection
    in each frame (-1: occluded / missing), ``occluded_frames`` (T, N) the O_i(k) used by the gate."""

    mean: np.ndarray
    cov: np.ndarray
    assignment: np.ndarray
    occluded_frames: np.ndarray


class MultiTargetTracker(Estimator):
    """Tracker of §2.2 (see the module docstring).

    Parameters
    ----------
    Q : (4, 4) array_like, default 0.01 I
    R : (2, 2) array_like, default I (px²)
    P0 : (4, 4) array_like, default diag(1, 10, 1, 10)
    gate0 : float, default 10 (px)   :math:`T_o`
    gate_slope : float, default 2 (px/frame)   :math:`\\alpha`
    mu : float, default 0   position weight in B
    warmup : int, default 5   frames associated against the previous measurements
    feedback : {"corrected", "printed", "off"}, default "corrected"
    second_map : {"closest", "mutual"}, default "closest"
    gate : bool, default True   (False: no gating, for the comparison of Exp. 3)
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        Keyword-only. The form of the shared update (:func:`~tobitkf.filters.core.measurement_update`).
        ``"standard"`` (Miller §2.2 uses the standard KF update (2.3)-(2.6),
        :math:`P = \\bar P - KC\\bar P`) is the faithful default; ``"joseph"`` the algebraically equal
        Joseph form; ``"square_root"`` (ours, not in the source) carries the Cholesky factor :math:`S`
        (``state.S``, :math:`P = SS^T`, lower triangular with a nonnegative diagonal, shared (1, 4, 4)
        like P until a miss) through the QR array forms of :func:`~tobitkf.filters.core.sqrt_predict`
        and :func:`~tobitkf.filters.core.sqrt_update`, so every covariance is PSD by construction, also
        for a huge prior with a near-singular R (P0 = 1e8 I, R = 1e-12 I), where the standard form's
        position variances after the first update are 0 or a multiple of 1.5e-8 instead of 1e-12 (in
        the tested case three later ones are also indefinite). The three agree to rounding otherwise
        (tested to 1e-10); the square-root form costs about 1.6 times the standard one.

    Raises
    ------
    ValidationError
        A gate0 <= 0, a negative gate_slope, NaN/inf/text/booleans for a number, a warm-up that is
        not an integer >= 0, ``gate`` not a bool, unknown options (a ``covariance_update`` other
        than "standard", "joseph", "square_root"); in :meth:`filter`, :meth:`step` and
        :meth:`track`, NaN, inf or text in a detection frame.
    ShapeError
        A detection frame that is not (L, 2).

    Notes
    -----
    The model matrices are kept as read-only copies (attributes ``A``, ``C``, ``Q``, ``R``, ``P0``,
    ``B``): the steps reuse what was computed from them. The reused predict is keyed on the form and
    on the bytes of what the step reads (P in the standard and Joseph forms, the factor S in the
    square-root form), so a different covariance or factor is never given another's prediction.
    """

    _name = "MultiTargetTracker"
    n, m = 4, 0

    def __init__(
        self,
        *,
        Q: Any = None,
        R: Any = None,
        P0: Any = None,
        gate0: float = 10.0,
        gate_slope: float = 2.0,
        mu: float = 0.0,
        warmup: int = 5,
        feedback: str = "corrected",
        second_map: str = "closest",
        gate: bool = True,
        covariance_update: str = "standard",
    ):
        check_option(covariance_update, "covariance_update", COVARIANCE_FORMS)
        check_option(feedback, "feedback", ("corrected", "printed", "off"))
        check_option(second_map, "second_map", ("closest", "mutual"))
        gate0 = as_float(gate0, "gate0", low=0.0, low_open=True)
        gate_slope = as_float(gate_slope, "gate_slope", low=0.0)
        mu = as_float(mu, "mu")
        warmup = check_int(warmup, "warmup", minimum=0)
        gate = check_bool(gate, "gate")
        self.A, self.C = constant_velocity_pixel_model()
        self.Q = 0.01 * np.eye(4) if Q is None else as_float_array(Q, "Q")
        self.R = np.eye(2) if R is None else as_float_array(R, "R")
        self.P0 = np.diag([1.0, 10.0, 1.0, 10.0]) if P0 is None else as_float_array(P0, "P0")
        for name, M, k in (("Q", self.Q, 4), ("R", self.R, 2), ("P0", self.P0, 4)):
            if M.shape != (k, k):
                raise ShapeError(f"{name}: expected shape ({k}, {k}), got {M.shape}")
            check_psd(M, name, strict=(name == "R"))
        self.B = np.diag([mu, 1.0, mu, 1.0])
        # the tracker's constants as private read-only copies: the predict below is memoized on them
        self.A, self.C, self.Q, self.R, self.P0, self.B = map(
            _constant, (self.A, self.C, self.Q, self.R, self.P0, self.B)
        )
        self.gate0, self.gate_slope, self.warmup = gate0, gate_slope, warmup
        self.feedback, self.second_map, self.gate = feedback, second_map, gate
        self.covariance_update = covariance_update
        self._G = _constant(psd_sqrt(self.Q))  # G G^T = Q: the process-noise root of the square-root predict
        self._R1 = self.R[None]  # (1, 2, 2): the noise shared by the targets
        self._no_input = Transition(A=self.A, Qd=self.Q, b=0.0, G=self._G)  # the predict of a frame without feedback
        self._feedback_free = feedback == "off"
        self._AT, self._BT, self._CT = self.A.T, self.B.T, self.C.T
        # ((form, shape, bytes) of what the predict reads (P, or S in the square-root form), P̄ = sym(A P A^T + Q),
        # S̄ or None): the last covariance predict,
        # reused when the next one starts from the same P (S) bit for bit in the same form
        self._last_predict: tuple | None = None
        # (the prior the update read (that P̄, or S̄ in the square-root form), the gain K (4, 2), the posterior
        # P and S (or None) computed from it): the last update of a reused prediction
        self._last_update: tuple | None = None

    def _feedback(self, x: np.ndarray, visible: np.ndarray) -> np.ndarray:
        N = x.shape[0]
        u = np.zeros_like(x)
        if self.feedback == "off" or N < 2:
            return u
        if self.feedback == "printed":
            # (2.16)-(2.17) as printed: own minus mean of all others, applied to targets in the frame
            others = (x.sum(axis=0) - x) / (N - 1)
            return (x - others) * visible[:, None]
        if not visible.any():
            return u
        for i in np.flatnonzero(~visible):
            vis = visible.copy()
            vis[i] = False
            if vis.any():
                u[i] = x[vis].mean(axis=0) - x[i]
        return u

    # ---- the estimator -------------------------------------------------------------------
    # the tracker starts from initial locations and takes one frame of detections per step, not Estimator's arguments
    def init(self, initial: Any = None, *, batch_shape: Any = None, x0: Any = None, P0: Any = None) -> FilterState:  # type: ignore[override]
        """Frame 0: one filter per target at the supplied locations ``initial`` (N, 2), zero velocity."""
        if initial is None:
            raise ValidationError("initial: expected the (N, 2) target locations of frame 0")
        init = as_float_array(initial, "initial")
        if init.ndim != 2 or init.shape[1] != 2 or init.shape[0] < 1:
            raise ShapeError(f"initial: expected (N, 2) target locations, got {init.shape}")
        N = init.shape[0]
        x = np.zeros((N, 4))
        x[:, 0], x[:, 2] = init[:, 0], init[:, 1]
        P = self.P0[None].copy()  # one covariance shared by the targets until one of them misses a frame
        S = psd_sqrt(P) if self.covariance_update == "square_root" else None
        carry = {"O": np.zeros(N, dtype=int), "visible": np.ones(N, dtype=bool), "last_meas": init.copy()}
        return mark_trusted(self, FilterState(k=0, batch_shape=(N,), x=x, P=P, n=4, S=S, carry=carry))

    def _frame(self, frame: Any, name: str = "detections") -> np.ndarray:
        """One frame as (L, 2) finite pixel coordinates; (2,) is one point, an empty array none."""
        if type(frame) is np.ndarray and frame.dtype == np.float64 and frame.ndim == 2 and frame.shape[1] == 2:
            # the common case, a float (L, 2) array: one finiteness pass (check_finite names the culprit); a few
            # points as Python floats (the same verdict, without the numpy calls)
            ok = all(map(math.isfinite, frame.ravel().tolist())) if frame.size <= 16 else np.isfinite(frame).all()
            if not ok:
                check_finite(frame, name)
            return frame if frame.size else np.zeros((0, 2))
        M = as_float_array(frame, name)
        if M.size == 0:
            return np.zeros((0, 2))
        if M.shape == (2,):
            return M[None, :]
        if M.ndim != 2 or M.shape[-1] != 2:
            raise ShapeError(f"{name}: expected (L, 2) points (x, y), got shape {M.shape}")
        return M

    def _distances(self, ref: np.ndarray, M: np.ndarray) -> tuple[list[list[float]], bool]:
        r"""The distances :math:`D_{ij} = \|y_i - m_j\|` (N, L) as lists, and whether they are all finite.

        A few pairs are computed in Python floats, many with one array expression; both evaluate
        :math:`\sqrt{d_x d_x + d_y d_y}` with the same IEEE operations, so the numbers are the same."""
        if len(ref) * len(M) <= _FEW_PAIRS:
            pts = M.tolist()
            D = []
            for rx, ry in ref.tolist():
                row = []
                for mx, my in pts:
                    dx, dy = rx - mx, ry - my
                    row.append(math.sqrt(dx * dx + dy * dy))
                D.append(row)
            # a sum is finite only if every term is (an overflowing sum takes the general route, which is exact too)
            return D, math.isfinite(sum(map(sum, D)))
        d = ref[:, None, :] - M[None, :, :]
        Da = np.sqrt(np.add.reduce(d * d, axis=-1))  # (N, L): np.linalg.norm(d, axis=-1), without its wrapper
        return Da.tolist(), bool(np.isfinite(Da).all())

    def _nearest(self, ref: np.ndarray, M: np.ndarray) -> tuple[list[int], list[float], bool]:
        r"""Each target's nearest detection :math:`j(i)` (the first of equal minima, as argmin), its distance
        :math:`D_{ij(i)}` and whether every distance is finite, for a few pairs in Python floats in one pass
        without the matrix D: the first map of :meth:`_associate`, the distances evaluated as in
        :meth:`_distances` (the same IEEE operations, so the same numbers). What the closest second map
        needs (the mutual one reads D's columns)."""
        pts = M.tolist()
        sqrt, inf = math.sqrt, math.inf
        first, near = [], []
        total = 0.0
        for rx, ry in ref.tolist():
            best, jbest, j = inf, 0, 0
            for mx, my in pts:
                dx, dy = rx - mx, ry - my
                d = sqrt(dx * dx + dy * dy)
                total += d
                if d < best:  # strictly: the first of equal minima
                    best, jbest = d, j
                j += 1
            first.append(jbest)
            near.append(best)
        # a sum is finite only if every term is (an overflowing sum takes the general route, which is exact too)
        return first, near, math.isfinite(total)

    def _associate(self, D: list[list[float]], O: list[int]) -> list[int]:
        r"""The nearest-neighbour assignment on finite distances D (N, L) as lists: each target's
        nearest detection :math:`j(i)` (the first of equal minima, as argmin), then :meth:`_assign`.
        Returns ``match`` (N,): the matched detection of each target, -1 for none."""
        first = [row.index(min(row)) for row in D]  # argmin: the first of equal minima
        return self._assign(first, [row[j] for row, j in zip(D, first)], O, D)

    def _assign(
        self, first: list[int], near: list[float], O: list[int], D: list[list[float]] | None = None
    ) -> list[int]:
        r"""The second map and the gate on each target's nearest detection ``first`` (N,) at the finite
        distance ``near`` (N,): the closest of the targets choosing one detection wins it (the first on a
        tie, as argmin), within the gate :math:`\|y_i - m_j\| < T_o + \alpha O_i`; the mutual second map
        also reads the distances ``D`` (N, L). Python loops over a few targets cost far less than the numpy
        calls per detection they replace. Returns ``match`` (N,): the matched detection of each target, -1
        for none."""
        winner: dict[int, int] = {}
        for i, j in enumerate(first):
            w = winner.get(j)
            if w is None or near[i] < near[w]:  # a later chooser wins only when strictly closer
                winner[j] = i
        match = [-1] * len(first)
        mutual, gated, T0, alpha = self.second_map == "mutual", self.gate, self.gate0, self.gate_slope
        for j, i in winner.items():
            if mutual:
                assert D is not None, "the mutual second map reads the distances"
                col = [row[j] for row in D]
                if col.index(min(col)) != i:
                    continue
            if not gated or near[i] < T0 + alpha * O[i]:
                match[i] = j
        return match

    def _associate_nonfinite(self, D: np.ndarray, O: np.ndarray) -> list[int]:
        """:meth:`_associate` for distances with NaN or inf (a diverged track): numpy's argmin rules for NaN."""
        N = D.shape[0]
        match = [-1] * N
        first = np.argmin(D, axis=1)
        dist = D[np.arange(N), first]
        for j in np.unique(first):
            choosers = np.flatnonzero(first == j)
            best = choosers[np.argmin(dist[choosers])]
            if self.second_map == "mutual" and np.argmin(D[:, j]) != best:
                continue
            if not self.gate or dist[best] < self.gate0 + self.gate_slope * O[best]:
                match[int(best)] = int(j)
        return match

    def _all_visible(self, N: int) -> np.ndarray:
        """The visibility of a frame that matched all ``N`` targets: one read-only all-True array per N, shared
        by the states of such frames (nothing writes a state's visibility; a new frame makes a new one)."""
        cache = self.__dict__.setdefault("_visible_cache", {})
        arr = cache.get(N)
        if arr is None:
            arr = cache[N] = np.ones(N, dtype=bool)
            arr.setflags(write=False)
        return arr

    def _step_arrays(self, k, x, P, S, carry, y, u, options=None):
        frame = options["frame"]
        if options.get("finite"):  # one frame from step(), already checked finite by _frame
            M = frame
        else:  # a row (1, L, 2) of filter()'s padded frames: its first `count` points are the frame
            M = frame[0, : int(options["count"][0])]
        N = x.shape[0]
        O, visible, last_meas = carry["O"], carry["visible"], carry["last_meas"]
        # the feedback input is zero for every target without feedback, for one target, or with every
        # target visible in the corrected form: the predict then adds nothing (x + 0 is x)
        input_free = self._feedback_free or N < 2 or (self.feedback == "corrected" and all(visible.tolist()))
        # P̄ does not depend on the data: once the covariance stops changing (the Riccati recursion at
        # its fixed point in floating point) every frame predicts the same P̄ from the same P, and the
        # predict of the last frame is passed on as the Transition's fixed covariance (the mean is
        # still A x + b, the same expression)
        form = self.covariance_update
        sqrt = form == "square_root"
        read = S if sqrt else P  # what the predict reads: the factor S in the square-root form, else P
        key, last = (form, read.shape, read.tobytes()), self._last_predict
        reused = last is not None and last[0] == key
        if reused:
            # the fixed covariance route: x̄ = A x + b (the same expression as the full predict) and the cached P̄
            Pp, Sp = last[1], last[2]
            if (
                input_free
            ):  # time_update's fixed-covariance branch written out, x A^T + b with b = 0 (.dot: @'s product)
                xp = x.dot(self._AT) + 0.0
            else:
                b = self._feedback(x, visible) @ self._BT
                xp, Pp, _ = time_update(x, P, S, Transition(A=self.A, Qd=self.Q, b=b, G=self._G, P_fixed=Pp), form)
        else:
            if input_free:
                tr = self._no_input
            else:
                tr = Transition(A=self.A, Qd=self.Q, b=self._feedback(x, visible) @ self._BT, G=self._G)
            xp, Pp, Sp = time_update(x, P, S, tr, form)
            Sp = _cholesky_signs(Sp)
            Pp.setflags(write=False)  # shared by the frames that reuse it
            if Sp is not None:
                Sp.setflags(write=False)
            self._last_predict = (key, Pp, Sp)
        # the predicted positions; ndarray.dot is the BLAS product of @ (the same numbers) without the
        # matmul ufunc's dispatch, which costs more than the product for these (N, 4) x (4, 2) arrays
        Cx = xp.dot(self._CT)
        ref = last_meas if k - 1 < self.warmup else Cx
        Ol = O.tolist()
        finite = False
        if len(M) and self.second_map == "closest" and len(ref) * len(M) <= _FEW_PAIRS:
            first, near, finite = self._nearest(ref, M)  # the first map without the matrix D
            match = (
                self._assign(first, near, Ol)
                if finite
                else self._associate_nonfinite(np.array(self._distances(ref, M)[0]), O)
            )
        elif len(M):
            D, finite = self._distances(ref, M)
            match = self._associate(D, Ol) if finite else self._associate_nonfinite(np.array(D), O)
        else:
            match = [-1] * N
        assignment = np.array(match, dtype=int)
        if -1 not in match:  # every target matched: the masks below would select everything (the same numbers)
            z = M.take(assignment, axis=0)
            valid, visible, new_O, new_last = None, self._all_visible(N), np.zeros(N, dtype=O.dtype), z
        else:
            visible = assignment >= 0
            z = np.where(visible[:, None], M[np.maximum(assignment, 0)] if len(M) else 0.0, 0.0)
            valid = np.repeat(visible[:, None], 2, axis=1)
            new_O, new_last = np.where(visible, 0, O + 1), np.where(visible[:, None], z, last_meas)
        # a covariance shared by the targets (P (1, 4, 4)) stays shared while every target is matched;
        # the first frame that misses one makes the update return one covariance per target
        last_up = self._last_update
        prior = Sp if sqrt else Pp  # what the update reads
        if valid is None and finite and ref is Cx and last_up is not None and last_up[0] is prior:
            # the reused prediction (the very object of the predict memo, so the same form and the same
            # P̄ or S̄) with every target matched and finite predicted positions: the gain K and the
            # posterior of the last such update, as a fixed gain (x = x̄ + K e); taken only for a gain
            # with at most one nonzero per row (the default decoupled x/y model), where K e is one
            # rounded product per component in any order of summation, the same numbers as the full update
            # measurement_update's fixed-gain branch written out (x̄ + K e, e = z - C x̄, which is finite here:
            # the frame is checked finite and the predicted positions are): the same expression
            xn, Pn, Sn = xp + (z - Cx).dot(last_up[1].T), last_up[2], last_up[3]  # .dot: @'s product, as Cx
        else:
            mp = MeasurementPrediction(expected=Cx, H0=self.C, noise=self._R1, valid=valid)
            xn, Pn, Sn, K, _ = measurement_update(xp, Pp, Sp, z, mp, form)
            Sn = _cholesky_signs(Sn)
            if reused and valid is None and K.shape[0] == 1 and int((K[0] != 0).sum(axis=1).max()) <= 1:
                Pn.setflags(write=False)  # shared by the frames that reuse it
                if Sn is not None:
                    Sn.setflags(write=False)
                self._last_update = (prior, K[0], Pn, Sn)
        new = {"O": new_O, "visible": visible, "last_meas": new_last}
        return xn, Pn, Sn, new, xp, Pp, {"assignment": assignment, "occluded_frames": O.copy()}

    def step(self, state: FilterState, detections: Any) -> FilterState:  # type: ignore[override]  # one frame per step
        """Track one frame of unordered detections (L, 2) (L may be 0)."""
        state = entering_state(self, state)
        M = self._frame(detections)
        k = state.k + 1
        x, P, S, carry, _, _, extras = self._step_arrays(
            k, state.x, state.P, state.S, state.carry, None, None, {"frame": M, "finite": True}
        )
        return mark_trusted(self, step_state(k, state.batch_shape, x, P, 4, S, carry, extras))

    def filter(  # type: ignore[override]  # its record is a sequence of detection frames, not readings (..., T, m)
        self, detections: Sequence[Any], *, initial: Any = None, state: FilterState | None = None, outputs: Any = "all"
    ) -> FilterResult:
        """Track every frame of ``detections`` (a sequence of T arrays (L_k, 2)) from ``initial`` (N, 2)
        or a ``state``; the common :class:`FilterResult` with the targets as runs: ``mean`` (N, T, 4),
        ``cov`` (N, T, 4, 4), ``extras`` ``assignment`` and ``occluded_frames`` (N, T), ``times`` 1..T."""
        if state is None:
            state = self.init(initial)
        elif initial is not None:
            raise ValidationError("state: give either a state to continue from or the initial locations, not both")
        state = entering_state(self, state)
        if (
            isinstance(detections, (str, bytes))
            or not hasattr(detections, "__len__")
            or not hasattr(detections, "__getitem__")
        ):
            raise ValidationError(
                f"detections: expected a sequence of (L_k, 2) arrays, one per frame, got {type(detections).__name__}"
            )
        frames = [self._frame(detections[i], f"detections[{i}]") for i in range(len(detections))]
        T = len(frames)
        if T == 0:
            raise ShapeError("detections: expected at least one frame")
        L = max(1, max(len(f) for f in frames))
        padded = np.full((1, T, L, 2), np.nan)
        for i, f in enumerate(frames):
            padded[0, i, : len(f)] = f
        N = state.runs
        counts = np.array([[len(f) for f in frames]])
        res = self._run(np.zeros((N, T, 0)), outputs=outputs, state=state, step_data={"frame": padded, "count": counts})
        # a covariance the targets shared throughout comes back as a read-only broadcast view: the
        # tracker's results stay ordinary (N, T, ...) arrays
        full: dict[str, Any] = {
            key: np.array(val)
            for key in ("cov", "pred_cov", "var")
            if (val := getattr(res, key)) is not None and not val.flags.writeable
        }
        return replace(res, **full) if full else res

    def _prepare_record(self, y, name="y"):
        # the loop's record is an empty (N, T, 0) placeholder: the frames travel as step data
        return y, y.shape[:1]

    def track(self, initial: Any, detections: Sequence[Any]) -> TrackResult:
        """Track from ``initial`` (N, 2) locations at frame 0 through ``detections``: a sequence of T arrays (L_k, 2)
        of unordered points (L_k may be 0). The frame-major layout of :class:`TrackResult`; see :meth:`filter`."""
        res = self.filter(detections, initial=initial)
        assert res.mean is not None and res.cov is not None, "the tracker records means and covariances"
        return TrackResult(
            np.swapaxes(res.mean, 0, 1),
            np.swapaxes(res.cov, 0, 1),
            np.swapaxes(res.extras["assignment"], 0, 1),
            np.swapaxes(res.extras["occluded_frames"], 0, 1),
        )


def _tracker(system, parts, o):
    return MultiTargetTracker(**o)


register(
    family_entry(
        MultiTargetTracker,
        "multi-target tracker leaving a field of view (Miller §2.2)",
        options={
            "gate0": float,
            "gate_slope": float,
            "mu": float,
            "warmup": int,
            "feedback": ("corrected", "printed", "off"),
            "second_map": ("closest", "mutual"),
            "gate": (False, True),
            "covariance_update": COVARIANCE_FORMS,
        },
        model="frames",
        factory=_tracker,
    )
)

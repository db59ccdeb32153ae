"""Which RSUs the bus filter trusts: each RSU's record of disagreement, the drift detector that flags
a camera whose fixes disagree persistently with the other RSUs' and the filter, and the assessment of
every RSU the filter reports (time offset, flag, disagreement, fix counts).

The evidence. A consistent filter's innovations (fix minus prediction, nu, with covariance S) are
white. A turned camera or a moved pole adds a bias to every fix of its RSU. Per RSU the filter
accumulates, with exponential forgetting over `window_s` (w = exp(-dt / window_s) between two fixes
of that RSU)::

    A = sum w S^-1,    A2 = sum w^2 S^-1,    b = sum w S^-1 nu
    m = A^-1 b          the weighted mean innovation (its fixes minus the filter, in x, y, yaw)
    C = A^-1 A2 A^-1    the covariance of m for white innovations
    T = b' A2^-1 b      chi-square, 3 dof: how persistent its disagreement with the filter is
    B = sum w B_k / sum w   its constant-bias covariance (below)

S is the innovation covariance without the fix's calibration share: a camera's calibration error is
common to every fix it makes (`Fix.calib_cov`, what the camera file's calibration covariance adds to
the fix; toptag.solvers.calibrated), so it does not average down with more fixes, as noise does. It is
B, the covariance of the RSU's constant bias, together with `bias_floor` (`drift_bias_sigma_m`,
`drift_bias_sigma_deg`: what a healthy RSU's fixes may be off by beyond their stated calibration, e.g.
the live pipeline's own per-RSU bias, `toptag eval livefix`). With `view_bias_share` s > 0 (the default,
0.76) B also holds what the fixes' view-dependent errors leave in m: fixes of a bus seen from one place (a
standing bus, one far tag) err alike, correlating as exp(-distance driven / `view_corr_m`), so they count
as one view, not one sample per frame (DriftRule.bias_cov); the rest of each fix's noise, (1 - s²) R, is
what S holds as white (`toptag eval livefix` fits s² = 0.58 over 6.35 m on the live pipeline's fixes).

A single wild fix cannot do much: nu is clipped to a Mahalanobis radius (`clip_sigma`, 10) before it
enters b, so it weighs like a 10-sigma fix at most. The radius is taken on S plus the drift thresholds
(`min_pos_m`, `min_yaw_rad`) as a covariance: on S alone, a precise RSU's innovations against a filter
that a turned camera pulls by 30 cm would be cut to a few cm, and precise and coarse RSUs, seeing the
same pull, would seem to disagree among themselves.

The test. The filter follows every RSU a little, and it may follow a wrong one a lot (it starts
from whichever RSU sees the bus first: if that camera is turned, the others look wrong to it). So an
RSU is judged against the other RSUs, through the filter: its deviation from the others is
d = m - mean(m of the others), with covariance C + sum(C of the others) / k², and T_d = d' (..)^-1 d
(the filter's own error, common to all, cancels), and the test is a Mahalanobis one against the noise
and the biases both: T_d = d' (C + sum C_o / k² + B + sum B_o / k²)^-1 d. A healthy RSU whose bias is
within its stated calibration uncertainty has T_d within the chi-square law however many fixes it
sends; a turned camera's grows until it is flagged. An RSU is flagged when
  - at least `min_others` other, unflagged RSUs have enough recent fixes (with one other the
    disagreement is symmetric: nobody can tell who is wrong),
  - T_d exceeds the chi-square quantile of `false_alarm`, over at least `min_fixes` of its fixes
    (effective count (sum w)^2 / sum w^2: a few wild fixes are not persistence),
  - |d| is larger than `min_pos_m` in position or `min_yaw_rad` in yaw (an optional floor; the
    bias covariance above is what says how large a healthy RSU's disagreement may be),
  - its time offset is known to `max_offset_sigma_s` (an offset being learnt looks like a bias
    along the track), and
  - the others agree among themselves: each one's deviation from the rest (without this RSU) has a
    T_d at most 1 / `isolation_ratio` of this RSU's.
It is cleared when, over at least `min_fixes` fixes again and with the others in view, T_d falls
below the `clear_probability` quantile and |d| is within the floor (old evidence fades with the window: a
camera seen agreeing on the next pass is cleared within a second or two; one still off by more than the
floor keeps its flag while its statistic dips).
Innovations enter only while the filter is healthy (tracking, a fix applied within the last second).
Innovations are only ever compared within one track: they start afresh for every RSU when the filter
jumps to a consensus it had rejected (reacquisition), for the others when an RSU is flagged, and for
all in a new filter (BusFilter.memory carries offsets and flags, not innovations). What a pass does
carry over to the next filter of the same bus is each RSU's deviation from the others (d and its noise
covariance, `RsuRecord.past`): the filter's error cancels in it, so it can be added up over passes
(forgetting over `past_window_s`) when a busy machine delivers too few fixes in one pass to decide.
It is dropped with everything else when another RSU is flagged (it was measured against that one).

The change test (`baseline_window_s` > 0). The same deviations, added up over a long time (a day), are
an RSU's long-run deviation from the others; its constant bias is in it as in this pass's, and cancels
in their difference Delta = d_now - d_long. A turn within what the calibration allows (not flagged by the
test above, which must allow the whole bias) is still a change: T_c = Delta' (C_now + C_long +
change_bias_share² B)^-1 Delta, the last term for how differently a camera's error moves fixes in other
parts of its view. It flags (`flagged_by` "change") at its own false-alarm quantile, with the same
conditions as above, and one more: the suspect's change must explain every other RSU's (had it alone
moved, by Delta, another's deviation would have moved by -lambda Delta / k, lambda in [0, 1] as far as
their evidence overlapped in time; each other's change less that, including RSUs seen earlier in the
pass and out of the window now, is at most 1 / isolation_ratio as significant). It clears when T_c
falls back. The first pass has no long run: the test above alone decides there. The long run is of one
calibration: when an RSU's fixes state another one (`Fix.calib_id`, the camera recalibrated) its
record starts afresh (RsuRecord.recalibrated).
While an RSU is flagged its fixes are down-weighted (covariance scaled and d d' added) or refused
(`FilterConfig.flagged_policy`); the filter, if it was following it, widens its pose by the others'
mean disagreement so that they can pull it back, and the others' evidence, gathered against that
filter, starts afresh; its fixes neither start a new filter nor keep the others' consensus from taking
the filter back (toptag.fusion.filter).

Pure: no I/O. Records are immutable (copy-on-write): the filter keeps one set per buffered step and
re-derives them on re-propagation, so an out-of-order replay ends with the same flags."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import numpy as np

from toptag.fusion import kernels
from toptag.units import s_from_ns

CALIBRATE_CHECK = "toptag calibrate check --camera CAM.json --points POINTS.json IMAGE"
# With a view-dependent error of share s (of each fix's sigma), the rest of its variance, (1 - s²) R, is white;
# at least this share of R is kept white, so that S stays well conditioned whatever s is.
MAX_VIEW_SHARE_OF_VARIANCE = 0.9
_Z33 = np.zeros((3, 3))  # stand-ins for the compiled arithmetic's absent arguments (never written)
_NO_RECORD = np.zeros((kernels.DA_LEN, 3, 3))
_NOWHERE = (math.nan, math.nan)  # an unknown place of the bus (drift_accumulate's xy)


class RsuRecord(NamedTuple):
    """What the filter knows of one RSU at one step."""
    last_t: int  # capture time of its newest fix processed
    clock_known: bool  # its newest fix came with a clock bound
    A: np.ndarray | None = None
    A2: np.ndarray | None = None
    b: np.ndarray | None = None
    stat: float = 0.0  # T: persistence of its disagreement with the filter
    n_eff: float = 0.0  # effective number of fixes in the statistic
    flagged_since: int | None = None
    # Its time offset (s) and variance (s²) when it had no slot in the state (given up, or carried
    # over from a previous filter), at time `offset_t`.
    offset: tuple[float, float] | None = None
    offset_t: int | None = None
    sums: tuple[float, float] = (0.0, 0.0)  # sum w, sum w^2 (for n_eff)
    m: np.ndarray | None = None  # mean innovation (x, y, yaw)
    C: np.ndarray | None = None  # its covariance
    deviation: np.ndarray | None = None  # d: m minus the others' mean, at its last decision
    deviation_stat: float = 0.0  # T_d
    others_mean: np.ndarray | None = None  # the others' mean innovation then
    Bs: np.ndarray | None = None  # sum w B_k: its fixes' calibration covariances, weighted as the innovations
    # Its deviation in this filter at its last decision (d, noise covariance, effective fixes), before any
    # earlier pass's was added: what memory() carries over.
    current: tuple | None = None
    # Deviations of earlier passes, added up (information form: sum C^-1, sum C^-1 d, fixes, time).
    past: tuple | None = None
    # Its long-run deviation from the others (the same form, fading over DriftRule.baseline_window_s): what
    # the change test compares this pass's deviation with. Its constant bias is in both and cancels.
    baseline: tuple | None = None
    flagged_by: str | None = None  # "others" (its deviation from them) or "change" (from its own long run)
    change: np.ndarray | None = None  # this pass's deviation minus the long-run one, at its last decision
    change_stat: float = 0.0  # its chi-square
    # The calibration its fixes say they were made with (Fix.calib_id): its long run is of that one only.
    calib_id: str | None = None
    # Its fixes' view-dependent error (DriftRule.view_bias_share): Q, the covariance of sum S^-1 L u of its
    # innovations (L the fix's noise sigma as a matrix, u common to fixes taken from nearby places), H its
    # running sum decayed by the distance driven, and where the bus was at the newest (x, y).
    Q: np.ndarray | None = None
    H: np.ndarray | None = None
    view_xy: tuple[float, float] | None = None
    # DriftRule.bias_cov of this record, kept by accumulate (None: computed when asked): every decision
    # asks for every RSU's, each the inverse of a 3x3 (~13 per fix with four RSUs).
    bias_c: np.ndarray | None = None
    # accumulate's results in one array (toptag.fusion.kernels.DA_ layout): A, A2, b, Bs, Q, H, m, C and bias_c
    # are views of it, and the next accumulate takes it whole
    block: np.ndarray | None = None

    @property
    def flagged(self) -> bool:
        return self.flagged_since is not None

    def bias(self) -> tuple[np.ndarray, np.ndarray]:
        """(m, C): its mean innovation and covariance (zeros before any fix)."""
        if self.m is None:
            return np.zeros(3), np.zeros((3, 3))
        return self.m, self.C

    def restart(self, keep_past: bool = True) -> RsuRecord:
        """The record without its innovations (its flag, clock and offsets kept; a flagged RSU keeps the
        disagreement it was flagged for, which down-weights its fixes until new evidence decides).
        keep_past=False: the earlier passes' deviations go too, and the long-run one."""
        past, baseline = (self.past, self.baseline) if keep_past else (None, None)
        rec = self._replace(A=None, A2=None, b=None, stat=0.0, n_eff=0.0, sums=(0.0, 0.0), m=None, C=None, Bs=None,
                            bias_c=None, block=None, current=None, past=past, baseline=baseline, change=None,
                            change_stat=0.0)
        return rec if self.flagged else rec._replace(deviation=None, deviation_stat=0.0, others_mean=None)

    def recalibrated(self, calib_id: str | None) -> RsuRecord:
        """The record of an RSU whose fixes now state another calibration (`Fix.calib_id`): its camera
        was recalibrated, so what it learnt of the old one goes (this pass's innovations, the earlier
        passes' and the long-run deviations); a flag stays until new evidence clears it."""
        return self.restart(keep_past=False)._replace(calib_id=calib_id)

    def disagreement(self) -> np.ndarray:
        """Its disagreement: the deviation from the other RSUs when known, else from the filter."""
        return self.deviation if self.deviation is not None else self.bias()[0]

    def statistic(self) -> float:
        """The chi-square of that disagreement (the deviation's when known, else the bias's)."""
        return self.deviation_stat if self.deviation is not None else self.stat


def _add_past(past: tuple | None, current: tuple, t_ns: int, window_s: float) -> tuple:
    """Earlier passes' deviations (information form, faded over `window_s` since they were added up)
    plus one more (d, C, n) at t_ns."""
    d, C, n = current
    try:
        I = np.linalg.inv(C)
    except np.linalg.LinAlgError:
        return past
    if past is None:
        return I, I @ d, float(n), int(t_ns)
    decay = math.exp(-s_from_ns(max(0, t_ns - past[3])) / window_s)
    return decay * past[0] + I, decay * past[1] + I @ d, decay * past[2] + float(n), int(t_ns)


def _mean(info: tuple) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(d, C, n) of deviations added up in information form, None if singular."""
    try:
        C = np.linalg.inv(info[0])
    except np.linalg.LinAlgError:
        return None
    return C @ info[1], C, info[2]


def _block(rec: RsuRecord) -> np.ndarray:
    """A record's sums as drift_accumulate takes them (kept by accumulate; built for a record made otherwise)."""
    if rec.block is not None:
        return rec.block
    blk = np.zeros((kernels.DA_LEN, 3, 3))
    blk[kernels.DA_A], blk[kernels.DA_A2], blk[kernels.DA_BS] = rec.A, rec.A2, rec.Bs
    if rec.H is not None:
        blk[kernels.DA_Q], blk[kernels.DA_H] = rec.Q, rec.H
    blk[kernels.DA_VEC, 0] = rec.b
    blk[kernels.DA_VEC, 2, :2] = rec.sums
    return blk


def _sqrtm(R: np.ndarray) -> np.ndarray:
    """The symmetric square root of a covariance: numpy's form of what drift_accumulate takes of R
    (toptag.fusion.kernels.sym_sqrt), kept as the reference its tests compare with."""
    w, V = np.linalg.eigh(R)
    return (V * np.sqrt(np.maximum(w, 0.0))) @ V.T


@dataclass(frozen=True)
class DriftRule:
    """The detector's thresholds (from FilterConfig)."""
    window_s: float
    flag_stat: float  # chi-square quantile of 1 - false_alarm, 3 dof
    clear_stat: float
    min_pos_m: float
    min_yaw_rad: float
    isolation_ratio: float
    clip_d2: float  # innovations are clipped to this Mahalanobis radius²
    min_fixes: float
    max_offset_sigma_s: float
    min_others: int = 2
    bias_floor: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # a healthy RSU's bias, beyond calibration
    min_other_fixes: float | None = None  # effective fixes another RSU needs to be compared with (None: min_fixes)
    past_window_s: float = 0.0  # earlier passes' deviations fade with this time constant (0: not kept)
    baseline_window_s: float = 0.0  # the long-run deviation fades with this (0: no change test)
    change_bias_share: float = 0.5  # how much of the bias may differ between the baseline's views and this pass
    change_flag_stat: float = math.inf  # the change test's chi-square quantile (its own false-alarm rate)
    view_bias_share: float = 0.0  # a fix's view-dependent error, as a share of its noise sigma (0: none)
    view_corr_m: float = 2.0  # ...common to fixes of one RSU taken within about this distance driven

    def accumulate(self, rec: RsuRecord, t_ns: int, nu: np.ndarray, S: np.ndarray,
                   B: np.ndarray | None = None, R: np.ndarray | None = None,
                   xy: tuple[float, float] | None = None) -> RsuRecord:
        """The record with one more innovation nu at t_ns: S its covariance without what the fix
        shares with every other fix of its RSU, B that share (its constant bias: the calibration's,
        the time offset's; None: none); R the fix's own noise covariance and xy where the bus was (for
        its view-dependent error: view_bias_share)."""
        # The arithmetic is compiled (toptag.fusion.kernels.drift_accumulate): as numpy it was ~25 small-array
        # calls per fix, re-run for every fix after a late one, the largest part of the bus agent's fix update.
        # The fix's noise is its view-dependent part plus the rest, white: S keeps (1 - s²) R of it, and the
        # view errors u of two fixes correlate as exp(-distance driven between them / view_corr_m): Q = sum_jk
        # X_j rho_jk X_k' (X = S^-1 R^1/2), kept with H = sum_k rho(now, k) X_k (both faded as b is).
        view = self.view_bias_share > 0 and R is not None and xy is not None
        first, w, view_first = self.fading(rec, t_ns)
        blk, ok = kernels.drift_accumulate(
            np.asarray(nu, dtype=float), np.asarray(S, dtype=float), _Z33 if B is None else np.asarray(B, dtype=float),
            _Z33 if R is None else np.asarray(R, dtype=float), self.previous(rec), *self.constants, w,
            np.array((*(_NOWHERE if xy is None else xy), *(rec.view_xy or _NOWHERE)), dtype=float), view, first,
            view_first)
        return self.accumulated(rec, t_ns, blk, ok, view, xy)

    def fading(self, rec: RsuRecord, t_ns: int) -> tuple[bool, float, bool]:
        """(first: no innovation before, w: the fading of the sums since the RSU's last fix, view_first: no
        view-error sums before), as accumulate's arithmetic takes them."""
        first = rec.A is None
        w = 0.0 if first else math.exp(-s_from_ns(max(0, t_ns - rec.last_t)) / self.window_s)
        return first, w, first or rec.H is None

    @staticmethod
    def previous(rec: RsuRecord) -> np.ndarray:
        """The record's sums as the arithmetic takes them (DA_ layout; zeros before its first innovation)."""
        return _NO_RECORD if rec.A is None else _block(rec)

    def accumulated(self, rec: RsuRecord, t_ns: int, blk: np.ndarray, ok: bool, view: bool, xy) -> RsuRecord:
        """The record with kernels.drift_accumulate's results (blk, ok) for the innovation at t_ns, the bus at
        xy."""
        if not ok:
            raise np.linalg.LinAlgError("singular innovation information in the drift detector")
        sw, sw2, stat = blk[kernels.DA_VEC, 2].tolist()
        return rec._replace(last_t=t_ns, A=blk[kernels.DA_A], A2=blk[kernels.DA_A2], b=blk[kernels.DA_VEC, 0],
                            stat=stat, n_eff=sw * sw / sw2, sums=(sw, sw2), m=blk[kernels.DA_VEC, 1],
                            C=blk[kernels.DA_C], Bs=blk[kernels.DA_BS], Q=blk[kernels.DA_Q] if view else None,
                            H=blk[kernels.DA_H] if view else None,
                            view_xy=(float(xy[0]), float(xy[1])) if view else rec.view_xy,
                            bias_c=blk[kernels.DA_BIAS], block=blk)

    def carry(self, rec: RsuRecord) -> RsuRecord:
        """The record with its deviation from the others in this filter added to the earlier passes'
        (faded by the time since), for the bus's next filter (its innovations go: see restart)."""
        past, baseline = rec.past, rec.baseline
        if not rec.flagged and rec.current is not None:
            if self.past_window_s > 0:
                past = _add_past(past, rec.current, rec.last_t, self.past_window_s)
            if self.baseline_window_s > 0:
                baseline = _add_past(baseline, rec.current, rec.last_t, self.baseline_window_s)
        return rec._replace(past=past, baseline=baseline).restart()

    def bias_cov(self, rec: RsuRecord) -> np.ndarray:
        """The covariance of an RSU's constant bias: its fixes' calibration share (weighted mean over
        the window) plus the floor, plus what its fixes' view-dependent errors leave in its mean
        innovation (view_bias_share² A^-1 Q A^-1: fixes taken from one place, e.g. of a standing bus,
        share theirs and do not average it down)."""
        if rec.bias_c is not None:
            return rec.bias_c
        return self._bias_cov(rec.Bs, rec.sums[0], rec.Q, None if rec.A is None else np.linalg.inv(rec.A))

    def _bias_cov(self, Bs: np.ndarray | None, sw: float, Q: np.ndarray | None, Ai: np.ndarray | None) -> np.ndarray:
        """bias_cov from a record's sums (Ai: the inverse of its A)."""
        B = self.bias_floor if Bs is None else Bs / sw + self.bias_floor
        if Q is not None and Ai is not None:
            B = B + self.view_bias_share ** 2 * (Ai @ Q @ Ai)
        return B

    @cached_property
    def constants(self) -> tuple[np.ndarray, np.ndarray]:
        """drift_accumulate's floors and consts of this rule."""
        return self._floors, self._consts

    @cached_property  # the rule is frozen: accumulate's constants once
    def _floors(self) -> np.ndarray:
        return np.stack((self._floor, np.asarray(self.bias_floor, dtype=float)))

    @cached_property
    def _consts(self) -> np.ndarray:
        return np.array([self.clip_d2, min(self.view_bias_share ** 2, MAX_VIEW_SHARE_OF_VARIANCE),
                         self.view_bias_share ** 2, self.view_corr_m], dtype=float)

    @cached_property
    def _floor(self) -> np.ndarray:
        """The smallest disagreement that counts as drift, as a covariance: the clip's scale is never
        below it. Clipped on the fix's own S alone, a precise RSU's innovations against a filter that a
        turned camera pulls by 30 cm would count as a few cm, and its mean innovation would understate
        what every other precise RSU sees (they would then seem to disagree among themselves)."""
        return np.diag([self.min_pos_m ** 2, self.min_pos_m ** 2, self.min_yaw_rad ** 2])

    def _beyond_floor(self, d: np.ndarray) -> bool:
        """Larger than a floor that is set (a floor of 0 is none)."""
        return (0 < self.min_pos_m < math.hypot(d[0], d[1])) or (0 < self.min_yaw_rad < abs(d[2]))

    def _large(self, d: np.ndarray) -> bool:
        return math.hypot(d[0], d[1]) > self.min_pos_m or abs(d[2]) > self.min_yaw_rad

    def _deviation(self, rec: RsuRecord, others: list[RsuRecord], t_ns: int) -> tuple:
        """(d, T_d, the others' mean, n, (d, noise covariance, n) in this filter alone) of one record
        against others: d and n with the earlier passes' deviations added (when kept), T_d against the
        noise and the biases of both."""
        # compiled: this runs 1 + k times per decision; from the records' drift_accumulate blocks where all have
        # one (every record the filter makes with an innovation), else from their fields
        if rec.block is not None and all(o.block is not None for o in others):
            out = kernels.drift_deviations(rec.block, np.array([o.block for o in others]))
            d, mo, T_d, Cn, Cb = out[0, 0], out[0, 1], float(out[0, 2, 0]), out[1], out[2]
        else:
            d, T_d, mo, Cn, Cb = kernels.drift_deviation(
                rec.m, rec.C, self.bias_cov(rec), np.array([o.m for o in others]), np.array([o.C for o in others]),
                np.array([self.bias_cov(o) for o in others]))
        current = (d, Cn, rec.n_eff)
        n = rec.n_eff
        if rec.past is not None and self.past_window_s > 0:
            I, Id, n, _ = _add_past(rec.past, current, t_ns, self.past_window_s)
            try:
                Cn = np.linalg.inv(I)
            except np.linalg.LinAlgError:
                pass
            else:
                d = Cn @ Id
                T_d = kernels.chi2(d, Cn + Cb)
        return d, T_d, mo, n, current

    def _change(self, rec: RsuRecord, current: tuple, others: list[RsuRecord], t_ns: int) -> tuple | None:
        """(Delta, T_c, its covariance): this pass's deviation from the others minus its long-run one, and
        its chi-square against their noise and the part of the biases that may differ between where the
        bus was seen then and now (change_bias_share: a camera's error moves a fix differently across its
        view); the constant bias itself cancels. None without a long-run deviation of at least min_fixes
        fixes."""
        if rec.baseline is None or self.baseline_window_s <= 0:
            return None
        base = _mean(rec.baseline)
        if base is None or base[2] < self.min_fixes:
            return None
        k = len(others)
        Cb = self.bias_cov(rec) + sum(self.bias_cov(o) for o in others) / (k * k)
        delta = current[0] - base[0]
        C = current[1] + base[1] + self.change_bias_share ** 2 * Cb
        return delta, kernels.chi2(delta, C), C

    def decide(self, records: dict[str, RsuRecord], rsu: str, t_ns: int,
               offset_sigma_s: float = 0.0) -> RsuRecord:
        """The record of `rsu` (just updated at t_ns) with its deviation from the others and its flag
        decided; `offset_sigma_s`: the uncertainty of its time offset now."""
        rec = records[rsu]
        window_ns = self.window_s * 1e9
        need = self.min_fixes if self.min_other_fixes is None else self.min_other_fixes
        others = {k: o for k, o in records.items()
                  if k != rsu and not o.flagged and o.m is not None and t_ns - o.last_t <= window_ns
                  and o.n_eff >= need}
        if len(others) < self.min_others or rec.m is None:
            return rec  # nobody to compare with: the flag stays as it is
        rest = list(others.values())
        if rec.flagged:  # cleared on this filter's evidence alone (a recalibrated camera, a camera turned back)
            d, T_d, mo, n, current = self._deviation(rec._replace(past=None), rest, t_ns)
            rec = rec._replace(deviation=d, deviation_stat=T_d, others_mean=mo, current=current)
            change = self._change(rec, current, rest, t_ns) if rec.flagged_by == "change" else None
            if change is not None:
                rec = rec._replace(change=change[0], change_stat=change[1])
            calm = (change[1] if change is not None else T_d) < self.clear_stat
            # and no longer as large as a flag needs (with a floor set): a camera still 4-5 cm off whose
            # statistic dips for a moment (its view error agreeing with the others') keeps its flag
            # instead of losing it for a second and taking it back.
            calm = calm and not self._beyond_floor(d if change is None else change[0])
            if calm and n >= self.min_fixes:
                return rec._replace(flagged_since=None, flagged_by=None)
            return rec
        d, T_d, mo, n, current = self._deviation(rec, rest, t_ns)
        rec = rec._replace(deviation=d, deviation_stat=T_d, others_mean=mo, current=current)
        change = self._change(rec, current, rest, t_ns)
        if change is not None:
            rec = rec._replace(change=change[0], change_stat=change[1])
        if offset_sigma_s > self.max_offset_sigma_s:
            return rec
        if T_d > self.flag_stat and n >= self.min_fixes and self._large(d) and self._isolated(others, T_d, t_ns):
            return rec._replace(flagged_since=t_ns, flagged_by="others", past=None)
        if change is not None and change[1] > self.change_flag_stat and current[2] >= self.min_fixes \
                and self._large(change[0]) and self._isolated(others, change[1], t_ns) \
                and self._explains(rsu, change, records, t_ns):
            return rec._replace(flagged_since=t_ns, flagged_by="change", past=None)
        return rec

    def _isolated(self, others: dict[str, RsuRecord], stat: float, t_ns: int) -> bool:
        """Do the others agree among themselves (without the RSU under test)? Each one's deviation from
        the rest has a chi-square at most 1 / isolation_ratio of `stat`."""
        for k, o in others.items():
            rest = [x for j, x in others.items() if j != k]
            if rest and self.isolation_ratio * self._deviation(o, rest, t_ns)[1] > stat:
                return False
        return True

    def _explains(self, rsu: str, change: tuple, records: dict[str, RsuRecord], t_ns: int) -> bool:
        """Does the suspect's change explain every other RSU's? Had only the suspect moved (by Delta), an
        other RSU's deviation from the others (the suspect among k of them) would have moved by -Delta / k
        where its evidence overlapped the suspect's in time, and not at all where it did not: by
        -lambda Delta / k, lambda in [0, 1]. So each other unflagged RSU with a long run, in view now or
        seen earlier in this pass, has its own change less the best such share at most 1 / isolation_ratio
        as significant as the suspect's change. A healthy RSU whose deviation a turned one moved (the turned
        one out of the window now) is not flagged for it: the turned one's change is not explained."""
        live = {k: x for k, x in records.items() if x.m is not None and not x.flagged}
        for k, o in live.items():
            if k == rsu or o.current is None:
                continue
            everyone = [x for j, x in live.items() if j != k]
            c = self._change(o, o.current, everyone, t_ns) if everyone else None
            if c is None:
                continue
            share = change[0] / len(everyone)
            try:
                W_share = np.linalg.solve(c[2], share)
            except np.linalg.LinAlgError:
                continue
            denom = float(share @ W_share)
            lam = 0.0 if denom <= 0 else min(1.0, max(0.0, -float(c[0] @ W_share) / denom))
            if self.isolation_ratio * kernels.chi2(c[0] + lam * share, c[2]) > change[1]:
                return False
        return True


@dataclass(frozen=True)
class RsuAssessment:
    """The bus filter's view of one RSU (toptag.fusion.filter.BusFilter.rsu_assessments)."""
    rsu: str
    offset_s: float | None  # estimated time offset (stamp minus exposure, in the bus's time), s
    offset_sigma_s: float | None
    clock_known: bool  # its fixes say how its clock is disciplined (a bound on the offset)
    flagged: bool
    flagged_since_ns: int | None
    disagreement: tuple[float, float, float]  # its fixes minus the other RSUs' (x m, y m, yaw rad), through the filter
    disagreement_sigma: tuple[float, float, float]
    statistic: float  # chi-square (3 dof) of the disagreement (T_d; T before others were in view)
    last_fix_ns: int
    fixes: dict[str, int] = field(default_factory=dict)  # outcome -> count (final decisions)
    policy: str = "downweight"
    # "others": it disagrees with the other RSUs beyond its calibration; "change": its fixes moved against
    # the others' since its earlier passes (disagreement and statistic are then that move's)
    flagged_by: str | None = None

    @property
    def disagreement_m(self) -> float:
        return math.hypot(self.disagreement[0], self.disagreement[1])

    @property
    def advice(self) -> str | None:
        """What the operator should do, for a flagged RSU."""
        if not self.flagged:
            return None
        what = "refused" if self.policy == "refuse" else "down-weighted"
        size = f"{100 * self.disagreement_m:.1f} cm / {math.degrees(abs(self.disagreement[2])):.2f} deg"
        if self.flagged_by == "change":
            return (f"camera {self.rsu} has moved: its fixes shifted by {size} against the other RSUs' since its "
                    f"earlier passes (turned, or its pole moved); its fixes are {what}; check its calibration: "
                    f"{CALIBRATE_CHECK}")
        return (f"camera {self.rsu} disagrees with the other RSUs and the fused track by {size}: its fixes "
                f"are {what}; check its calibration: {CALIBRATE_CHECK}")


__all__ = ["CALIBRATE_CHECK", "DriftRule", "RsuAssessment", "RsuRecord"]

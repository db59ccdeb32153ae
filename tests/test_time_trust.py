"""Time and trust in the bus filter: each RSU's time offset estimated in the state, drifted cameras
flagged and down-weighted, every fix's path counted; the same in any arrival order. Fixes come from
the fusion study's error model with the simulator's faults (sim.faults)."""
import json
import math

import numpy as np
import pytest

from sim.faults import RsuFault, faults_from_options
from sim.motion import ImuModel, bus_trajectory
from sim.studies.fusion import STUDY_DRIFT_THRESHOLDS, FixErrorModel, simulate_fixes
from toptag.fix import Fix
from toptag.fusion.filter import BusFilter, FilterConfig
from toptag.fusion.offsets import pose_before
from toptag.fusion.outcomes import FixOutcome
from toptag.fusion.trust import CALIBRATE_CHECK

pytestmark = pytest.mark.unit

MS = 1_000_000


def study_filter(memory=None, **config) -> BusFilter:
    """A bus filter with the fusion study's drift thresholds: these tests feed it the study's unbiased fixes."""
    return BusFilter(FilterConfig(**(STUDY_DRIFT_THRESHOLDS | config)), memory=memory)


@pytest.fixture(scope="module")
def turn():
    traj = bus_trajectory("left", "w", seed=0)
    imu = ImuModel().synthesize(traj, 0.0, traj.duration, np.random.default_rng(21))
    return traj, imu


def fixes_with(traj, faults: dict, seed: int = 5) -> list[Fix]:
    return simulate_fixes(traj, FixErrorModel(), 4, np.random.default_rng(seed), faults=faults)


def arrivals(fixes, faults, delay_ms=100.0, jitter_ms=0.0, seed=0):
    """(arrival on the bus clock, fix): exposure + latency + delay; stamp = exposure + latency + offset."""
    rng = np.random.default_rng(seed)
    out = []
    for f in fixes:
        clock = faults.get(f.source, RsuFault()).clock_offset_ms
        out.append((f.t_ns - int(clock * MS) + int((delay_ms + jitter_ms * rng.uniform(-1, 1)) * MS), f))
    return out


def drive(flt, imu, arr, on_output=None):
    """Feed IMU rows (an ImuSamples or a list of its rows) and (arrival, fix) in time order."""
    arr = sorted(arr, key=lambda a: a[0])
    j = 0
    for k, (t_ns, g, ax, ay, w) in enumerate(imu if isinstance(imu, list) else imu.rows()):
        while j < len(arr) and arr[j][0] < t_ns:
            flt.add_fix(arr[j][1], arrival_ns=arr[j][0])
            j += 1
        flt.add_imu(t_ns, g, ax, ay, w)
        if on_output is not None and k % 10 == 0 and flt.initialized:
            on_output(t_ns)
    for a, f in arr[j:]:
        flt.add_fix(f, arrival_ns=a)
    return flt


def pos_err(est, traj):
    st = traj.state_at_ns(est.t_ns)
    return math.hypot(est.x - st.x, est.y - st.y)


# ----------------------------------------------------------------------------- the model
def test_pose_before_jacobians_match_finite_differences():
    x = np.array([3.0, -2.0, 0.7, 7.5, 0.4, 0.01, 0.02])
    for delta in (0.0, 0.03, -0.05):
        h, Hs, Hd = pose_before(x, delta, accel=0.8)
        eps = 1e-6
        for j in range(5):
            dx = np.zeros(7)
            dx[j] = eps
            num = (pose_before(x + dx, delta, 0.8)[0] - pose_before(x - dx, delta, 0.8)[0]) / (2 * eps)
            assert np.allclose(Hs[:, j], num, atol=1e-7), (delta, j)
        num = (pose_before(x, delta + eps, 0.8)[0] - pose_before(x, delta - eps, 0.8)[0]) / (2 * eps)
        assert np.allclose(Hd, num, atol=1e-7)
    # 40 ms at 7.5 m/s heading 0.7 rad: the bus was 30 cm back along its heading
    h, _, _ = pose_before(np.array([0.0, 0.0, 0.7, 7.5, 0.0, 0.0, 0.0]), 0.04, 0.0)
    assert np.allclose(h[:2], -0.3 * np.array([math.cos(0.7), math.sin(0.7)]))


def test_an_unknown_offset_widens_the_gate_along_the_track_only(turn):
    """A new RSU with an unknown clock: its fix 25 cm ahead along the track is what a 30 ms offset
    makes (accepted); 25 cm across the track is no offset at all (rejected)."""
    traj, imu = turn
    base = fixes_with(traj, {})
    rows = [r for r in imu.rows() if r[0] <= traj.t_ns(2.0)]
    outcomes = {}
    for name, direction in (("along", 0.0), ("across", math.pi / 2)):
        flt = study_filter()
        drive(flt, rows, [(f.t_ns + 50 * MS, f) for f in base if f.t_ns < traj.t_ns(1.8)])
        st = traj.state_at(1.95)
        a = st.yaw + direction
        probe = Fix(traj.t_ns(1.95), st.x + 0.25 * math.cos(a), st.y + 0.25 * math.sin(a), st.yaw,
                    np.diag([0.03 ** 2, 0.03 ** 2, math.radians(0.1) ** 2]), "rsu-new", 0, clock_bound_ns=None)
        outcomes[name] = flt.add_fix(probe, arrival_ns=rows[-1][0])
    assert outcomes == {"along": FixOutcome.ACCEPTED, "across": FixOutcome.REJECTED_GATE}


# ----------------------------------------------------------------------------- offsets
@pytest.mark.parametrize("spec", ["rsu-se=30", "rsu-se=60,rsu-ne=60"])
def test_rsu_offsets_are_estimated_within_3ms_in_one_pass(turn, spec):
    traj, imu = turn
    faults = faults_from_options(clock_offset_ms=spec)
    flt = drive(study_filter(), imu, arrivals(fixes_with(traj, faults), faults, jitter_ms=30))
    a = flt.rsu_assessments()
    assert set(a) == {"rsu-sw", "rsu-se", "rsu-ne", "rsu-nw"}
    for rsu, v in a.items():
        injected = faults[rsu].time_offset_ns / MS if rsu in faults else 0.0
        assert abs(1e3 * v.offset_s - injected) < 3.0, (rsu, v)
        assert 1e3 * v.offset_sigma_s < 3.0
        assert v.clock_known == (rsu not in faults)  # an offset clock says it is undisciplined
    assert pos_err(flt.estimate(), traj) < 0.05
    h = flt.estimate().health
    n_unknown = sum(1 for f in fixes_with(traj, faults) if f.source in faults)
    assert h.unknown_clock == n_unknown > 0



def _unknown_clocks(fixes):
    return [f.replace(clock_bound_ns=None) for f in fixes]


def test_with_no_clock_known_the_first_rsu_is_the_time_reference(turn):
    """Every RSU's clock unknown (recordings that do not say, hosts without chrony): their common
    offset is seen only through the bus's turns, so the filter follows the first RSU's time and
    estimates the others' against it; one 30 ms RSU is still found, and the track is as good as
    with known clocks."""
    traj, imu = turn
    faults = faults_from_options(clock_offset_ms="rsu-se=30")
    arr = arrivals(fixes_with(traj, faults), faults, jitter_ms=30)
    errs = {}
    for name, feed in (("known", arr), ("unknown", [(a, g) for (a, _), g in zip(arr, _unknown_clocks(f for _, f in arr))])):
        flt, e = study_filter(), []
        drive(flt, imu, feed, on_output=lambda t, flt=flt, e=e: e.append(pos_err(flt.estimate(t), traj)))
        errs[name] = math.sqrt(np.mean(np.square(e)))
        if name == "unknown":
            a = flt.rsu_assessments()
            ref = [k for k, v in a.items() if 1e3 * v.offset_sigma_s <= 5.0 + 1e-6]
            assert abs(1e3 * (a["rsu-se"].offset_s - np.mean([v.offset_s for k, v in a.items() if k != "rsu-se"]))
                       - 30.0) < 3.0
            assert ref and all(abs(1e3 * v.offset_s) < 10.0 for k, v in a.items() if k != "rsu-se")
            assert flt.estimate().health.unknown_clock == len(feed)
    assert errs["unknown"] < 1.3 * errs["known"] + 0.005, errs


def test_a_known_clock_releases_the_time_reference_by_widening_it(turn):
    """The reference's offset was held to the known-clock prior; once an RSU with a known clock takes
    a slot, that variance is given back (an inflation: the offset's sigma grows, nothing shrinks)."""
    traj, imu = turn
    fixes = sorted(fixes_with(traj, {}), key=lambda f: f.t_ns)
    first = next(f for f in fixes if f.source == "rsu-sw")
    other = next(f for f in fixes if f.source != "rsu-sw" and f.t_ns > first.t_ns)
    rows = [r for r in imu.rows() if r[0] <= other.t_ns + 20 * MS]
    flt = study_filter()
    drive(flt, rows, [(first.t_ns + MS, _unknown_clocks([first])[0])])
    before = flt.rsu_assessments()["rsu-sw"].offset_sigma_s
    flt.add_fix(other, arrival_ns=rows[-1][0])
    after = flt.rsu_assessments()["rsu-sw"].offset_sigma_s
    assert 1e3 * before == pytest.approx(5.0, abs=0.5) and after > 2 * before  # (the new fix ties it again)

def test_capture_latency_on_a_disciplined_clock_is_estimated_too(turn):
    traj, imu = turn
    faults = faults_from_options(capture_latency_ms="rsu-nw=25")
    flt = drive(study_filter(), imu, arrivals(fixes_with(traj, faults), faults))
    v = flt.rsu_assessments()["rsu-nw"]
    assert v.clock_known and abs(1e3 * v.offset_s - 25.0) < 3.0


# ----------------------------------------------------------------------------- ordering
def test_out_of_order_replay_reproduces_offsets_and_flags_bit_for_bit(turn):
    traj, imu = turn
    faults = faults_from_options(clock_offset_ms="rsu-ne=40", drift_deg="rsu-se=0.5@2")
    fixes = fixes_with(traj, faults, seed=8)
    in_order = arrivals(fixes, faults, delay_ms=150.0)
    rng = np.random.default_rng(3)
    shuffled = [(a - 150 * MS + int(rng.uniform(20, 600)) * MS, f) for a, f in in_order]
    first = min(fixes, key=lambda f: f.t_ns)
    shuffled = [(min(a for a, _ in shuffled) - 1, first)] + [s for s in shuffled if s[1] is not first]
    a, b = drive(study_filter(), imu, in_order), drive(study_filter(), imu, shuffled)
    ea, eb = a.estimate(), b.estimate()
    assert np.array_equal(ea.state, eb.state) and np.array_equal(ea.state_cov, eb.state_cov)
    ra, rb = a.rsu_assessments(), b.rsu_assessments()
    assert ra.keys() == rb.keys()
    for k in ra:
        assert (ra[k].offset_s, ra[k].offset_sigma_s, ra[k].flagged_since_ns, ra[k].disagreement) == \
               (rb[k].offset_s, rb[k].offset_sigma_s, rb[k].flagged_since_ns, rb[k].disagreement), k
    assert ra["rsu-se"].flagged and abs(1e3 * ra["rsu-ne"].offset_s - 40) < 3
    assert ea.health.from_flagged_rsu == eb.health.from_flagged_rsu > 0


# ----------------------------------------------------------------------------- drift
def test_a_turned_camera_is_flagged_and_down_weighted_the_others_not(turn):
    traj, imu = turn
    faults = faults_from_options(drift_deg="rsu-se=0.3@2")
    times = {}
    flt = study_filter()

    def watch(t_ns):
        for rsu in flt.estimate(t_ns).health.flagged_rsus:
            times.setdefault(rsu, traj.seconds(t_ns))
    drive(flt, imu, arrivals(fixes_with(traj, faults), faults), on_output=watch)
    a = flt.rsu_assessments()
    assert set(times) == {"rsu-se"} and a["rsu-se"].flagged
    assert not any(v.flagged for k, v in a.items() if k != "rsu-se")
    se = a["rsu-se"]
    assert 0.02 < se.disagreement_m < 0.15 and abs(math.degrees(se.disagreement[2])) > 0.15  # the bus yaw turns too
    assert CALIBRATE_CHECK in se.advice and "down-weighted" in se.advice
    h = flt.estimate().health
    assert h.flagged_rsus == ("rsu-se",) and h.from_flagged_rsu > 0
    assert pos_err(flt.estimate(), traj) < 0.05


# ----------------------------------------------------------------------------- the live pipeline's traps
# Each of these let the live faults demo flag a healthy RSU after the turned one (issue 13; the offline
# replay of its fixes is in docs/time-and-trust.md).
def _exact_fixes(traj, source, every_s=0.1, shift=(0.0, 0.0, 0.0), sigma=(0.01, 0.01, 0.002), t_from=0.0):
    """Fixes at the true pose plus a constant shift, with a known clock, reporting `sigma`."""
    out = []
    for k, t in enumerate(np.arange(t_from, traj.duration, every_s)):
        st = traj.state_at_ns(traj.t_ns(float(t)))
        out.append(Fix(t_ns=int(traj.t_ns(float(t))), x=st.x + shift[0], y=st.y + shift[1], yaw=st.yaw + shift[2],
                       cov=np.diag(np.square(sigma)), source=source, seq=k, clock_bound_ns=MS))
    return out


def test_start_up_takes_no_fix_from_a_flagged_rsu_nor_one_older_than_its_imu(turn):
    traj, imu = turn
    rows = list(imu.rows())
    old = study_filter()
    drive(old, rows, arrivals(fixes_with(traj, faults_from_options(drift_deg="rsu-se=0.5@2")), {}))
    assert old.memory()["rsu-se"].flagged
    new = study_filter(memory=old.memory())
    se = _exact_fixes(traj, "rsu-se")[20]
    for r in rows[:25]:
        new.add_imu(*r)
    assert new.add_fix(se, arrival_ns=rows[24][0]) is FixOutcome.NOT_INITIALIZED and not new.initialized
    assert new.counters()["from_flagged_rsu"] == 1
    late = study_filter(buffer_s=1.0)
    for r in rows[:300]:  # 3 s of IMU: the first 2 s are gone from the start-up buffer
        late.add_imu(*r)
    stale = _exact_fixes(traj, "rsu-nw")[5]
    assert late.add_fix(stale, arrival_ns=rows[299][0]) is FixOutcome.TOO_OLD and not late.initialized
    assert late.add_fix(_exact_fixes(traj, "rsu-nw")[25], arrival_ns=rows[299][0]) is FixOutcome.INITIALIZED


def test_a_new_filter_remembers_flags_and_offsets_not_the_evidence(turn):
    traj, imu = turn
    faults = faults_from_options(drift_deg="rsu-se=0.5@2")
    old = drive(study_filter(), imu, arrivals(fixes_with(traj, faults), faults))
    mem = old.memory()
    assert mem["rsu-se"].flagged and mem["rsu-se"].deviation is not None  # what it was flagged for
    assert all(r.m is None and r.n_eff == 0 and r.offset is not None for r in mem.values())
    assert all(r.deviation is None for k, r in mem.items() if k != "rsu-se")


def test_a_flagged_rsus_fixes_do_not_keep_the_others_consensus_out(turn):
    """The filter follows rsu-sw, flagged but with a small remembered disagreement, whose fixes are
    20 cm off: the others' fixes fail the gate, and the flagged camera's down-weighted fixes, applied
    meanwhile, neither reset their consensus nor count as the filter being on track: the others
    take it back within about `reacquire_after_s`."""
    traj, imu = turn
    old = study_filter()
    drive(old, imu, arrivals(fixes_with(traj, faults_from_options(drift_deg="rsu-sw=0.5@0")), {}))
    mem = old.memory()
    assert mem["rsu-sw"].flagged
    mem["rsu-sw"] = mem["rsu-sw"]._replace(deviation=np.array([0.01, 0.0, 0.0]))
    flt = study_filter(memory=mem)
    st = traj.state_at_ns(traj.t_ns(1.0))
    flt.initialize(traj.t_ns(1.0), st.x, st.y + 0.2, st.yaw, cov=np.diag([1e-4, 1e-4, 1e-6]), speed=st.speed,
                   trusted=True)
    fixes = _exact_fixes(traj, "rsu-sw", shift=(0.0, 0.2, 0.0), t_from=1.05) + \
        [f for src in ("rsu-ne", "rsu-nw") for f in _exact_fixes(traj, src, t_from=1.07)]
    drive(flt, [r for r in imu.rows() if r[0] > traj.t_ns(1.0)], arrivals(fixes, {}))
    per = flt.counters()["per_source"]
    assert per["rsu-ne"].get("reacquired", 0) + per["rsu-nw"].get("reacquired", 0) >= 1
    assert per["rsu-ne"]["accepted"] > 0.8 * sum(per["rsu-ne"].values())
    assert pos_err(flt.estimate(), traj) < 0.05
    assert not any(a.flagged for k, a in flt.rsu_assessments().items() if k != "rsu-sw")


def test_a_flagged_rsus_fixes_move_no_time_offset(turn):
    """A turned camera's bias along the track would pass for a late clock: its fixes, down-weighted,
    still move the pose, not the other RSUs' time offsets (nor its own, held since it was flagged)."""
    traj, imu = turn
    old = study_filter()
    faults = faults_from_options(drift_deg="rsu-sw=0.5@0", clock_offset_ms="rsu-ne=40")
    drive(old, imu, arrivals(fixes_with(traj, faults), faults))
    assert old.memory()["rsu-sw"].flagged
    flt = study_filter(memory=old.memory())
    rows = list(imu.rows())
    fixes = [f for f in fixes_with(traj, faults, seed=9) if f.source != "rsu-sw" and f.t_ns < traj.t_ns(5.0)]
    drive(flt, [r for r in rows if r[0] <= traj.t_ns(5.0)], arrivals(fixes, faults))
    before = {k: (a.offset_s, a.offset_sigma_s) for k, a in flt.rsu_assessments().items()}
    st = traj.state_at_ns(flt.head_ns)  # at the newest step: no later fix is re-applied
    outcome = flt.add_fix(Fix(t_ns=flt.head_ns, x=st.x + 0.05, y=st.y, yaw=st.yaw, cov=np.diag([25e-4, 25e-4, 1e-5]),
                              source="rsu-sw", seq=99_999, clock_bound_ns=MS))
    assert outcome.applied
    after = {k: (a.offset_s, a.offset_sigma_s) for k, a in flt.rsu_assessments().items()}
    moved = {k: abs(after[k][0] - v[0]) for k, v in before.items() if v[0] is not None and k != "rsu-sw"}
    assert set(moved) == {"rsu-ne", "rsu-nw", "rsu-se"}
    assert max(moved.values()) < 1e-6  # < 1 us (the IMU update after it in the same step); 30 us if it taught them


def test_a_precise_rsu_shows_its_whole_disagreement_with_a_pulled_filter():
    """Innovations are clipped (one wild fix counts as 10 sigma at most), but never below the drift
    thresholds' scale: a 1 cm RSU 30 cm from a filter a turned camera pulled shows 30 cm, not 10 sigma."""
    rule = BusFilter(FilterConfig())._drift
    from toptag.fusion.trust import RsuRecord
    rec = RsuRecord(last_t=0, clock_known=True)
    S = np.diag([1e-4, 1e-4, 1e-6])
    for k in range(10):
        rec = rule.accumulate(rec, k * 100 * MS, np.array([0.3, 0.0, 0.0]), S)
    assert abs(rec.m[0] - 0.3) < 1e-9
    wild = rule.accumulate(rec, 1000 * MS, np.array([50.0, 0.0, 0.0]), S)
    assert wild.m[0] < 2.0  # clipped: 10 sigma of the thresholds' scale


def _view_case(share: float, step_m: float, sigma=(0.05, 0.23), err=(0.025, 0.3), n: int = 30) -> bool:
    """Four RSUs see a bus every 0.1 s, driving step_m metres between fixes; three are right, one errs by
    err (m across the track, deg in yaw) in every fix, each fix stating sigma (m, deg). Is that one flagged,
    with the 3 cm / 0.1 deg box and a view share `share`?"""
    from toptag.fusion.trust import RsuRecord
    rule = BusFilter(FilterConfig(drift_view_bias_share=share, drift_min_pos_m=0.03, drift_min_yaw_deg=0.1))._drift
    R = np.diag([sigma[0] ** 2, sigma[0] ** 2, math.radians(sigma[1]) ** 2])
    S = R + np.diag([0.01 ** 2, 0.01 ** 2, math.radians(0.03) ** 2])  # plus the filter's own uncertainty
    rng = np.random.default_rng(3)
    recs = {r: RsuRecord(last_t=0, clock_known=True) for r in ("rsu-sw", "rsu-se", "rsu-ne", "rsu-nw")}
    bias = np.array([0.0, err[0], math.radians(err[1])])
    for k in range(n):
        t = k * 100 * MS
        for r in recs:
            nu = 0.3 * rng.standard_normal(3) * np.sqrt(np.diag(R)) + (bias if r == "rsu-se" else 0.0)
            recs[r] = rule.accumulate(recs[r], t, nu, S, None, R, (k * step_m, 0.0))
            recs[r] = rule.decide(recs, r, t)
    return recs["rsu-se"].flagged


def test_fixes_from_one_place_do_not_average_their_error_down():
    """A standing bus seen from one place: every fix of a healthy RSU errs alike (its view's error, here
    1.3 stated sigmas in yaw, as rsu-se's did with bus-42 standing 21 m away in the compose demo). Counted as
    30 independent fixes it is a persistent disagreement (flagged with no view share); weighed as one
    view's error it is not. A camera turned by 0.2 deg, seen by precise fixes (1 cm, 0.05 deg) of a bus
    driving at 7 m/s, is flagged."""
    assert _view_case(share=0.0, step_m=0.0)
    assert not _view_case(share=1.0, step_m=0.0)
    assert _view_case(share=1.0, step_m=0.7, sigma=(0.01, 0.05), err=(0.035, 0.2))
    # the same with the default share (0.76: the live fixes' fitted 58 % of their variance)
    share = FilterConfig().drift_view_bias_share
    assert not _view_case(share=share, step_m=0.0)
    assert _view_case(share=share, step_m=0.7, sigma=(0.01, 0.05), err=(0.035, 0.2))


def test_a_flag_stays_over_passes_while_the_camera_is_still_off():
    """The 0.2 deg turn over four passes (left, straight, right, a stop) with the default settings, on fixes
    drawn as the live pipeline's, each pass's filter starting from the last one's memory: once flagged, the
    camera stays flagged. Standing at the stop, its statistic dipped below the clearing quantile while it
    still disagreed by more than the 3 cm / 0.1 deg box, and the flag went off and came back (as live, on
    the 0.2 deg scenario, twice in 300 s); a flag now clears only within the box."""
    from sim.studies.fusion import LIVE_VIEW_ERROR

    faults = faults_from_options(drift_deg="rsu-se=0.2@0")
    memory, history = None, []
    for k, route in enumerate(("left", "straight", "right", "stop")):
        tr = bus_trajectory(route, "w", seed=0, t0_ns=bus_trajectory(route, "w", seed=0).t0_ns + k * 60 * 10**9)
        imu = ImuModel().synthesize(tr, 0.0, tr.duration, np.random.default_rng(50 + k))
        fixes = simulate_fixes(tr, FixErrorModel(**LIVE_VIEW_ERROR), 4, np.random.default_rng(100 + k), faults=faults)
        flt = BusFilter(FilterConfig(), memory=memory)
        seen = lambda t: history.append((k, t, "rsu-se" in flt.rsu_assessments() and flt.rsu_assessments()["rsu-se"].flagged))
        drive(flt, imu, arrivals(fixes, faults, jitter_ms=30, seed=k), on_output=seen)
        memory = flt.memory()
    first = next(i for i, (_, _, f) in enumerate(history) if f)
    assert history[first][0] == 0  # flagged on the first pass
    assert all(f for _, _, f in history[first:]), [(k, t) for k, t, f in history[first:] if not f][:3]


def test_the_study_draws_view_dependent_errors_as_fitted():
    """The fusion study's default fix errors (LIVE_VIEW_ERROR, fitted by `toptag eval livefix`): each fix's
    error, in units of its stated sigma, has unit variance, and the share the fit says is common to the
    same RSU's fixes taken a few centimetres apart (a standing bus), none of it 30 m apart."""
    from sim.studies.fusion import LIVE_VIEW_ERROR

    model = FixErrorModel(**LIVE_VIEW_ERROR)
    near, far, zz = [], [], []
    for seed in range(6):
        traj = bus_trajectory("stop", "w", seed=0)
        fixes = simulate_fixes(traj, model, 4, np.random.default_rng(seed))
        by = {}
        for f in fixes:
            st = traj.state_at_ns(f.t_ns)
            e = np.array([f.x - st.x, f.y - st.y, math.remainder(f.yaw - st.yaw, 2 * math.pi)])
            by.setdefault(f.source, []).append((np.hypot(st.x, st.y), e / np.sqrt(np.diag(f.cov)), st))
        for rows in by.values():
            zz.extend(z for _, z, _ in rows)
            for (_, a, sa), (_, b, sb) in zip(rows, rows[1:]):
                if math.hypot(sa.x - sb.x, sa.y - sb.y) < 0.05:
                    near.append((a, b))
            for i in range(0, len(rows), 2):
                for j in range(i + 1, len(rows)):
                    if math.hypot(rows[i][2].x - rows[j][2].x, rows[i][2].y - rows[j][2].y) > 30:
                        far.append((rows[i][1], rows[j][1]))
    zz = np.array(zz)
    assert np.all(np.abs(np.sqrt((zz ** 2).mean(0)) - 1.0) < 0.15)
    rho = lambda pairs: np.mean([float(a @ b) for a, b in pairs]) / 3
    assert len(near) > 100 and abs(rho(near) - model.view_share) < 0.15
    assert len(far) > 100 and abs(rho(far)) < 0.15


def test_the_live_fits_correlation_and_share_are_recovered():
    """`toptag eval livefix`'s fit of rho(d) = share exp(-d / corr_m) over binned correlations."""
    from sim.studies.livefix import fit_view_correlation

    d = np.array([0.02, 0.1, 0.35, 0.75, 1.5, 3.0, 6.0, 12.0])
    share, L, res = fit_view_correlation(d, 0.6 * np.exp(-d / 5.0), np.full(len(d), 100.0))
    assert abs(share - 0.6) < 0.02 and 4.5 < L < 5.6 and res < 0.01


def test_the_defaults_flag_a_02_deg_turn_on_live_like_fixes_and_nothing_without(turn):
    """The issue's 0.2 deg step with the bus filter's default settings, on fixes drawn as the live pipeline's
    (the fusion study's default error model): flagged within 10 s of the bus in the camera's view, and the
    same fixes without the turn flag nothing."""
    from sim.studies.fusion import LIVE_VIEW_ERROR

    traj, imu = turn
    model = FixErrorModel(**LIVE_VIEW_ERROR)
    faults = faults_from_options(drift_deg="rsu-se=0.2@0")
    for seed in (1, 2):
        turned = drive(BusFilter(FilterConfig()), imu,
                       arrivals(simulate_fixes(traj, model, 4, np.random.default_rng(seed), faults=faults), faults))
        a = turned.rsu_assessments()
        first = min(f.t_ns for f in simulate_fixes(traj, model, 4, np.random.default_rng(seed)) if f.source == "rsu-se")
        assert a["rsu-se"].flagged and a["rsu-se"].flagged_since_ns - first < 10 * 10**9, (seed, a["rsu-se"])
        assert [r for r, v in a.items() if v.flagged] == ["rsu-se"]
        healthy = drive(BusFilter(FilterConfig()), imu,
                        arrivals(simulate_fixes(traj, model, 4, np.random.default_rng(seed)), {}))
        assert not any(v.flagged for v in healthy.rsu_assessments().values())


def test_refuse_policy_refuses_a_flagged_rsu(turn):
    traj, imu = turn
    faults = faults_from_options(drift_deg="rsu-se=0.3@2")
    flt = drive(study_filter(flagged_policy="refuse"), imu, arrivals(fixes_with(traj, faults), faults))
    c = flt.counters()
    assert c["refused_flagged"] > 0 and c["per_source"]["rsu-se"]["refused_flagged"] == c["refused_flagged"]
    assert "refused" in flt.rsu_assessments()["rsu-se"].advice


def test_the_flag_clears_once_the_camera_agrees_again(turn):
    """rsu-se is turned during one pass (flagged) and recalibrated before the next: the bus's next
    filter starts from what the last one learnt (flagged), and clears the flag once rsu-se agrees."""
    traj, imu = turn
    faults = faults_from_options(drift_deg="rsu-se=0.5@2")
    first = drive(study_filter(), imu, arrivals(fixes_with(traj, faults), faults))
    assert first.rsu_assessments()["rsu-se"].flagged
    later = bus_trajectory("left", "w", seed=0, t0_ns=traj.t0_ns + 120 * 10**9)
    imu2 = ImuModel().synthesize(later, 0.0, later.duration, np.random.default_rng(22))
    flagged = []
    second = study_filter(memory=first.memory())
    drive(second, imu2, arrivals(fixes_with(later, {}, seed=6), {}),
          on_output=lambda t: flagged.append((later.seconds(t), second.estimate(t).health.flagged_rsus)))
    assert flagged[0][1] == ("rsu-se",)  # still flagged when the next pass starts
    assert not second.rsu_assessments()["rsu-se"].flagged and flagged[-1][1] == ()
    cleared = next(t for t, f in flagged if f == ())
    in_view = min(later.seconds(f.t_ns) for f in fixes_with(later, {}, seed=6) if f.source == "rsu-se")
    assert cleared - in_view < 3.0


def test_no_flag_without_a_fault(turn):
    traj, imu = turn
    for seed in range(3):
        flt = drive(study_filter(), imu, arrivals(fixes_with(traj, {}, seed=seed), {}, jitter_ms=30, seed=seed))
        assert not any(v.flagged for v in flt.rsu_assessments().values())


CALIBRATED = FixErrorModel(calib_rot_sigma_deg=0.05, calib_trans_sigma=0.02)  # the image model's defaults


def test_a_calibration_error_within_its_stated_covariance_is_no_drift(turn):
    """Each camera stands off its surveyed pose by a draw of its stated calibration covariance (0.05 deg,
    2 cm per axis), so every one of its fixes carries the same bias, and says so (Fix.calib_cov, in cov):
    weighed as each RSU's constant bias, no healthy RSU is flagged; counted as noise (the detector
    before), the bias of some RSU looks ever more certain with every fix, and is flagged."""
    traj, imu = turn
    as_noise = []
    for seed in range(4):
        fixes = simulate_fixes(traj, CALIBRATED, 4, np.random.default_rng(seed))
        assert all(f.calib_cov is not None and np.all(np.linalg.eigvalsh(f.cov - f.calib_cov) > 0) for f in fixes)
        flt = drive(study_filter(), imu, arrivals(fixes, {}, jitter_ms=30, seed=seed))
        assert not any(v.flagged for v in flt.rsu_assessments().values()), seed
        old = drive(study_filter(drift_calibration_is_bias=False), imu, arrivals(fixes, {}, jitter_ms=30, seed=seed))
        as_noise += [k for k, v in old.rsu_assessments().items() if v.flagged]
    assert len(as_noise) >= 2


def test_a_turn_well_beyond_the_stated_calibration_is_still_flagged(turn):
    """0.3 deg on a camera calibrated to 0.01 deg / 5 mm (per axis): flagged, and no other RSU."""
    traj, imu = turn
    faults = faults_from_options(drift_deg="rsu-se=0.3@0")
    model = FixErrorModel(calib_rot_sigma_deg=0.01, calib_trans_sigma=0.005)
    for seed in range(2):
        fixes = simulate_fixes(traj, model, 4, np.random.default_rng(seed), faults=faults)
        flt = drive(study_filter(), imu, arrivals(fixes, faults))
        assert [k for k, v in flt.rsu_assessments().items() if v.flagged] == ["rsu-se"], seed


def test_a_flagged_rsus_time_offset_is_not_reported_and_restarts_once_cleared(turn):
    """A turned camera's bias along the track passes for a clock offset: once flagged, its offset is
    reset to its prior and reported as no estimate (excluded) while the flag stands; when the camera
    agrees again (the next pass, recalibrated) the flag clears and the offset is learnt afresh."""
    traj, imu = turn
    faults = faults_from_options(drift_deg="rsu-se=0.5@2")
    first = drive(study_filter(), imu, arrivals(fixes_with(traj, faults), faults))
    se = first.rsu_assessments()["rsu-se"]
    assert se.flagged and se.offset_s is None and se.offset_sigma_s is None
    assert all(v.offset_s is not None for k, v in first.rsu_assessments().items() if k != "rsu-se")
    i = first._steps[-1].g.clocks.index("rsu-se")
    assert abs(first._steps[-1].x[7 + i]) < 2e-3  # reset to its prior (0), moved since only through correlations
    from protocol.convert import assessment_to_message
    from services.monitor import _trust_cells

    m = assessment_to_message(se, "bus-17", "x1", first.head_ns)
    assert m.drift_flagged and m.time_offset_ns is None and m.time_offset_sigma_ns is None
    cells = _trust_cells({"time_offset_ms": {"bus-17": {"estimate": None, "sigma": None, "clock_known": True}},
                          "drift_flagged": True, "flagged_by": ["bus-17"]})
    assert "offset bus-17 excluded (flagged)" in cells and "DRIFT (bus-17" in cells
    later = bus_trajectory("left", "w", seed=0, t0_ns=traj.t0_ns + 120 * 10**9)
    imu2 = ImuModel().synthesize(later, 0.0, later.duration, np.random.default_rng(22))
    second = drive(study_filter(memory=first.memory()), imu2, arrivals(fixes_with(later, {}, seed=6), {}))
    se2 = second.rsu_assessments()["rsu-se"]  # recalibrated
    assert not se2.flagged and se2.offset_s is not None and abs(1e3 * se2.offset_s) < 3, se2
    assert se2.offset_sigma_s < 0.5 * math.sqrt(first.memory()["rsu-se"].offset[1])  # learnt again


def _starved(fixes, keep_per_rsu: int, seed: int) -> list:
    """What a busy machine delivers of one pass: a few fixes of each RSU, spread over its view."""
    rng = np.random.default_rng(seed)
    out = []
    for src in sorted({f.source for f in fixes}):
        mine = [f for f in fixes if f.source == src]
        out += [mine[k] for k in sorted(rng.choice(len(mine), min(keep_per_rsu, len(mine)), replace=False))]
    return sorted(out, key=lambda f: f.t_ns)


def test_on_a_starved_machine_the_turned_camera_is_flagged_over_passes(turn):
    """Each pass brings 8 fixes per RSU, too few for the 10 effective fixes a flag needs (the others are
    compared with from 3, as in toptag/data/demo/bus-faults.toml). An RSU's
    deviation from the others (the filter's error cancels in it) is carried from pass to pass by the
    bus's next filter (BusFilter.memory), so the turned camera is flagged after a few passes, and no
    other RSU; without it (drift_past_window_s = 0) it never is."""
    traj, imu = turn
    faults = faults_from_options(drift_deg="rsu-sw=0.5@0")
    flagged = {}
    for window in (120.0, 0.0):
        mem, when = None, None
        for k in range(5):
            t0 = traj.t0_ns + k * 60 * 10**9
            tr = bus_trajectory("left", "w", seed=0, t0_ns=t0)
            imu_k = ImuModel().synthesize(tr, 0.0, tr.duration, np.random.default_rng(30 + k))
            fixes = _starved(fixes_with(tr, faults, seed=40 + k), 8, k)
            flt = drive(study_filter(memory=mem, drift_past_window_s=window, drift_min_other_fixes=3), imu_k,
                        arrivals(fixes, faults))
            a = flt.rsu_assessments()
            assert not any(v.flagged for r, v in a.items() if r != "rsu-sw"), (window, k)
            if a["rsu-sw"].flagged and when is None:
                when = k
            mem = flt.memory()
        flagged[window] = when
    assert flagged[120.0] is not None and flagged[120.0] >= 1 and flagged[0.0] is None, flagged


def test_a_slow_ramp_is_flagged_once_the_turn_adds_up():
    """rsu-se's camera turns by 0.2 deg over 300 s (0.04 deg more at each pass of the bus, 60 s apart; the
    study's thresholds, each pass's filter from the last one's memory): it is flagged by the sixth pass
    (0.2 deg) at the latest, never on the first two (0 and 0.04 deg), and no other RSU ever is (`toptag eval fusion --drift-deg rsu-se=0.2@100/300 --passes 8`: flagged in 8/8 runs at
    0.08-0.17 deg)."""
    faults = faults_from_options(drift_deg="rsu-se=0.2@0/300")
    mem, when = None, None
    for k in range(6):
        tr = bus_trajectory("left", "w", seed=0, t0_ns=bus_trajectory("left", "w", seed=0).t0_ns + k * 60 * 10**9)
        imu = ImuModel().synthesize(tr, 0.0, tr.duration, np.random.default_rng(60 + k))
        fixes = simulate_fixes(tr, FixErrorModel(), 4, np.random.default_rng(80 + k), faults=faults, t_offset_s=60.0 * k)
        flt = drive(study_filter(memory=mem), imu, arrivals(fixes, faults, jitter_ms=30, seed=k))
        a = flt.rsu_assessments()
        assert not any(v.flagged for r, v in a.items() if r != "rsu-se"), (k, a)
        if a["rsu-se"].flagged and when is None:
            when = k
        mem = flt.memory()
    assert when is not None and when >= 2, when


WELL_CALIBRATED = FixErrorModel(calib_rot_sigma_deg=0.02, calib_trans_sigma=0.01)  # a realistic stated calibration


def _pass(k: int, cameras, faults: dict, seed: int, memory, calib_ids: dict | None = None, **config) -> BusFilter:
    """The bus's k-th pass (a left turn, 60 s after the last) seen by cameras standing off their surveyed
    poses (one calibration draw), its filter starting from the last one's memory; `calib_ids`: the
    calibration id that an RSU's fixes state (Fix.calib_id; None: not said)."""
    tr = bus_trajectory("left", "w", seed=0, t0_ns=bus_trajectory("left", "w", seed=0).t0_ns + k * 60 * 10**9)
    imu = ImuModel().synthesize(tr, 0.0, tr.duration, np.random.default_rng(50 + k))
    fixes = simulate_fixes(tr, WELL_CALIBRATED, 4, np.random.default_rng(100 * seed + k), faults=faults, cameras=cameras)
    if calib_ids:
        fixes = [f.replace(calib_id=calib_ids.get(f.source)) for f in fixes]
    return drive(study_filter(memory=memory, **config), imu, arrivals(fixes, faults, jitter_ms=30, seed=k))


def test_a_step_within_the_calibration_is_flagged_against_the_rsus_own_past():
    """A 0.2 deg turn of a camera calibrated to 0.02 deg / 1 cm is within what its calibration allows
    (the test against the others weighs its whole bias), but not within how its fixes compared with the
    others' on the bus's earlier passes, where its constant bias was the same: the change test flags it
    on the first pass after the step ("has moved", with the turn's size), and no other RSU; two passes
    without a fault flag nothing. With no long-run deviation kept (drift_baseline_window_s = 0) the turn
    goes unflagged. Nor is it flagged when rsu-se's fixes state a new calibration (Fix.calib_id: the camera
    was recalibrated, its long run starts afresh)."""
    from sim.studies.fusion import draw_cameras

    faults = faults_from_options(drift_deg="rsu-se=0.2@0")
    flagged = without = recalibrated = 0
    for seed in range(2):
        cams = draw_cameras(WELL_CALIBRATED, 4, np.random.default_rng(70 + seed))
        mem = None
        for k in range(2):
            flt = _pass(k, cams, {}, seed, mem)
            assert not any(v.flagged for v in flt.rsu_assessments().values()), (seed, k)
            mem = flt.memory()
        a = _pass(2, cams, faults, seed, mem).rsu_assessments()
        assert not any(v.flagged for r, v in a.items() if r != "rsu-se"), (seed, a)
        se = a["rsu-se"]
        if se.flagged:
            flagged += 1
            assert se.flagged_by == "change" and "has moved" in se.advice
            assert 0.1 < math.degrees(-se.disagreement[2]) < 0.3, se  # the turn's size, in the fixes' yaw
        without += _pass(2, cams, faults, seed, mem, drift_baseline_window_s=0.0).rsu_assessments()["rsu-se"].flagged
        new = _pass(2, cams, faults, seed, mem, calib_ids={"rsu-se": "recalibrated"})
        recalibrated += new.rsu_assessments()["rsu-se"].flagged
        after = new.memory()
        assert after["rsu-se"].calib_id == "recalibrated" and mem["rsu-se"].baseline is not None
        # its long run now holds this pass alone (one pass's fixes), the others' all three
        assert after["rsu-se"].baseline[2] < after["rsu-ne"].baseline[2] / 2, (after["rsu-se"].baseline[2],)
    assert flagged == 2 and without == 0 and recalibrated == 0, (flagged, without, recalibrated)


def test_a_change_flag_needs_the_suspect_to_explain_the_others_changes():
    """A turned camera (rsu-se) moves the others' deviations by a share of its turn; once it has left the
    window a healthy RSU (rsu-ne), whose fixes then seem shifted against rsu-sw and rsu-nw, must not be
    flagged for a change. rsu-se's own change, remembered from earlier in the pass,
    is not explained by rsu-ne's turning (which would move it by a third of rsu-ne's change at most), so
    rsu-ne is not flagged; without rsu-se's record it is (the case is one the change test decides)."""
    from toptag.fusion.trust import RsuRecord, _add_past

    rule = BusFilter(FilterConfig(**(STUDY_DRIFT_THRESHOLDS | dict(
        drift_bias_sigma_m=0.05, drift_bias_sigma_deg=0.5, drift_change_bias_share=0.0))))._drift
    C = np.diag([1e-4, 1e-4, math.radians(0.01) ** 2])  # each RSU's mean innovation: 1 cm, 0.01 deg
    turn = np.array([0.15, 0.0, math.radians(0.45)])  # rsu-se's move against the others

    def record(m, last_s, current=None):
        base = _add_past(None, (np.zeros(3), C, 50.0), 0, 86400.0)  # long run: no deviation
        return RsuRecord(last_t=last_s * 10**9, clock_known=True, m=np.asarray(m, float), C=C, n_eff=20.0,
                         sums=(20.0, 20.0), current=current, baseline=base)

    now = 300
    records = {"rsu-ne": record(-turn / 3, now), "rsu-sw": record(np.zeros(3), now),
               "rsu-nw": record(np.zeros(3), now),
               "rsu-se": record(turn, now - 20, current=(turn, 1.5 * C, 20.0))}  # out of the 5 s window
    without_se = {k: v for k, v in records.items() if k != "rsu-se"}
    alone = rule.decide(without_se, "rsu-ne", now * 10**9)
    assert alone.flagged and alone.flagged_by == "change", alone
    judged = rule.decide(records, "rsu-ne", now * 10**9)
    assert not judged.flagged and judged.change_stat > rule.change_flag_stat, judged


# ----------------------------------------------------------------------------- accounting
def test_every_fix_path_is_counted(turn):
    traj, imu = turn
    fixes = fixes_with(traj, {})
    flt = study_filter(buffer_s=1.0)
    rows = list(imu.rows())
    extra = [fixes[10].replace(seq=fixes[10].seq),  # a duplicate
             fixes[20].replace(x=float("nan"), seq=10_001),  # invalid
             fixes[30].replace(t_ns=fixes[30].t_ns + 3_000 * MS, seq=10_002),  # from the future
             fixes[40].replace(clock_bound_ns=None, seq=10_003, t_ns=fixes[40].t_ns + 1)]  # unknown clock
    arr = [(f.t_ns + 80 * MS, f) for f in fixes]
    arr += [(fixes[10].t_ns + 90 * MS, extra[0]), (fixes[20].t_ns + 90 * MS, extra[1]),
            (fixes[30].t_ns + 90 * MS, extra[2]), (fixes[40].t_ns + 90 * MS, extra[3])]
    arr += [(fixes[50].t_ns + 1_500 * MS, fixes[50].replace(seq=10_004, t_ns=fixes[50].t_ns + 2))]  # too old
    drive(flt, rows, arr)
    h = flt.estimate().health
    c = flt.counters()
    assert c["fixes"] == len(arr)
    assert h.accepted + h.rejected + h.too_old + h.future + c["refused_flagged"] + h.other == len(arr)
    assert h.too_old >= 1 and h.future >= 1 and h.unknown_clock == 1 and c["duplicate"] == 1 and c["invalid"] == 1


# ----------------------------------------------------------------------------- memory, slots
def test_a_new_filter_starts_from_what_the_last_one_learnt(turn):
    traj, imu = turn
    faults = faults_from_options(clock_offset_ms="rsu-ne=40", drift_deg="rsu-se=0.5@2")
    old = drive(study_filter(), imu, arrivals(fixes_with(traj, faults), faults))
    new = study_filter(memory=old.memory())
    rows = list(imu.rows())
    fixes = [f for f in fixes_with(traj, faults, seed=9) if f.t_ns < traj.t_ns(4.0)]
    drive(new, rows[:420], arrivals(fixes, faults))
    a = new.rsu_assessments()
    assert a["rsu-se"].flagged  # still flagged: nothing has cleared it
    assert abs(1e3 * a["rsu-ne"].offset_s - 40) < 3 and 1e3 * a["rsu-ne"].offset_sigma_s < 5


def test_a_remembered_offset_is_kept_when_a_known_clock_joins(turn):
    """The next filter starts from the unknown-clock rsu-ne, whose offset the last one learnt: it is an
    estimate, not the time reference's borrowed prior, so a known clock joining does not widen it back
    to the unknown clocks' prior (it did: 25 ms after a pass, in a replay of the faults demo)."""
    traj, imu = turn
    faults = faults_from_options(clock_offset_ms="rsu-ne=40")
    mem = drive(study_filter(), imu, arrivals(fixes_with(traj, faults), faults)).memory()
    fixes = fixes_with(traj, faults, seed=9)
    t_ne = min(f.t_ns for f in fixes if f.source == "rsu-ne")
    first = [f for f in fixes if f.source == "rsu-ne" and f.t_ns < t_ne + 500 * MS]
    then = [f for f in fixes if f.source != "rsu-ne" and t_ne + 500 * MS <= f.t_ns < t_ne + 700 * MS]
    assert first and then
    flt = drive(study_filter(memory=mem), list(imu.rows()), arrivals(first + then, faults))
    ne = flt.rsu_assessments()["rsu-ne"]
    assert abs(1e3 * ne.offset_s - 40) < 3 and 1e3 * ne.offset_sigma_s < 2 * 1e3 * math.sqrt(mem["rsu-ne"].offset[1]) + 1


def test_slots_are_given_up_least_recently_heard_first_and_remembered(turn):
    traj, imu = turn
    faults = faults_from_options(clock_offset_ms="rsu-sw=30")
    flt = drive(study_filter(max_offset_slots=2), imu, arrivals(fixes_with(traj, faults), faults))
    a = flt.rsu_assessments()
    assert len(a) == 4 and all(v.offset_s is not None for v in a.values())
    assert abs(1e3 * a["rsu-sw"].offset_s - 30) < 6  # seen first, given its slot up, remembered


# ----------------------------------------------------------------------------- the study
def test_fusion_study_writes_the_evidence_of_time_and_trust(tmp_path):
    from sim.studies import fusion

    res = fusion.run(tmp_path, [100], jitter_ms=30, seed=2, runs=2, plots=False, log=lambda *_: None,
                     progress=False, faults=faults_from_options(clock_offset_ms="rsu-ne=30",
                                                                drift_deg="rsu-se=0.3@3"))
    saved = json.loads((tmp_path / "results.json").read_text())
    case = saved["faulted"]["latency_ms"]["100"]
    assert math.isfinite(case["fused_pos_rms_m"]) and case["fused_over_fault_free"] < 1.5
    o = case["offset_estimate_ms"]["rsu-ne"]
    assert o["injected_ms"] == 30 and abs(o["final_ms_mean"] - 30) < 3 and o["sigma_ms_mean"] > 0
    d = case["drift_flagged"]
    assert d["rsu-se"]["injected"] and d["rsu-se"]["runs_flagged"] == 2 and d["rsu-se"]["delay_s_max"] < 10
    assert case["false_flags"] == 0 == saved["latency_ms"]["100"]["false_flags"]
    assert saved["time_and_trust"]["100"]["offsets_within_3ms_every_run"]
    assert res["setup"]["faults"].startswith("rsu-ne")
    # the default fix errors are the live pipeline's fitted ones, and the run says so
    assert "view-dependent" in saved["setup"]["fix_error_model"] and saved["setup"]["fix_model"]["view_share"] > 0


@pytest.mark.parametrize("argv, says", [
    (["--clock-offset-ms", "rsu-se"], "--clock-offset-ms: expected RSU=MS"),
    (["--drift-deg", "rsu-se=big"], "--drift-deg: expected RSU=DEG"),
    (["--clock-offset-ms", "rsu-xx=30"], "faults name RSUs the study does not have: rsu-xx"),
    (["--route", "left,loop"], "--route: unknown route(s) loop"),
    (["--bus-config", "BAD"], "drift_min_pos_mm: unknown key"),
])
def test_fusion_study_options_are_checked(tmp_path, capsys, argv, says):
    from sim.studies import fusion

    bad = tmp_path / "bad.toml"
    bad.write_text("[filter]\ndrift_min_pos_mm = 2.0\n")
    argv = [str(bad) if a == "BAD" else a for a in argv]
    assert fusion.main(["--out", str(tmp_path), "--runs", "1", "--no-plots", *argv]) == 2
    err = capsys.readouterr().err
    assert says in err and len(err.strip().splitlines()) == 1


# ----------------------------------------------------------------------------- on the wire
def test_wire_carries_the_clock_offsets_flags_and_fix_paths(turn):
    from protocol.codec import decode, encode
    from protocol.convert import assessment_to_message, fix_from_message, fix_to_message, fused_to_message
    from protocol.messages import ClockInfo, PoseFix, RsuDiagnosis

    traj, imu = turn
    fix = fixes_with(traj, {})[5].replace(z=3.0, method="level", tags=(3,), rms_px=0.2)
    for clock, bound in ((ClockInfo(source="ntp", sync_uncertainty_ns=700_000), 700_000),
                         (ClockInfo(source="system"), None), (None, None)):
        back = fix_from_message(fix_to_message(fix, "bus-17", "x1", fix.t_ns + 5 * MS, clock=clock))
        assert back.clock_bound_ns == bound and back.calib_cov is None
    calibrated = simulate_fixes(traj, CALIBRATED, 4, np.random.default_rng(1))[5].replace(
        z=3.0, method="level", tags=(3,), rms_px=0.2)
    back = fix_from_message(decode(encode(fix_to_message(calibrated, "bus-17", "x1", calibrated.t_ns)), PoseFix))
    assert np.allclose(back.calib_cov, calibrated.calib_cov) and np.allclose(back.cov, calibrated.cov)
    faults = faults_from_options(clock_offset_ms="rsu-ne=40", drift_deg="rsu-se=0.3@2")
    flt = drive(study_filter(), imu, arrivals(fixes_with(traj, faults), faults))
    t = flt.head_ns
    se = assessment_to_message(flt.rsu_assessments()["rsu-se"], "bus-17", "x1", t)
    ne = decode(encode(assessment_to_message(flt.rsu_assessments()["rsu-ne"], "bus-17", "x1", t)), RsuDiagnosis)
    assert se.drift_flagged and se.flagged_since_ns <= t and "toptag calibrate check" in se.advice
    assert se.disagreement_m > 0.02 and se.fixes_accepted > 0
    assert abs(ne.time_offset_ns / MS - 40) < 3 and ne.time_offset_sigma_ns < 3 * MS and not ne.clock_known
    h = fused_to_message(flt.estimate(), "bus-17").health
    assert h.flagged_rsus == ["rsu-se"] and h.flagged_rsu_fixes > 0 and h.unknown_clock_fixes > 0
    c = flt.counters()
    assert h.accepted_fixes + h.rejected_fixes + h.too_old_fixes + h.future_fixes + c["refused_flagged"] + \
        h.other_fixes == c["fixes"]


def test_fix_paths_add_up_across_filters(turn):
    """A bus agent starts a new filter after an IMU gap (the next pass): its health adds the earlier
    filters' fix counts (Health.plus_paths), so the paths count every fix since the agent started."""
    traj, imu = turn
    faults = faults_from_options(clock_offset_ms="rsu-se=30")
    first = drive(study_filter(), imu, arrivals(fixes_with(traj, faults), faults)).estimate().health
    p = first.paths()  # disjoint outcomes; unknown clock and flagged RSU are attributes across them
    assert p["accepted"] + p["rejected"] + p["too_old"] + p["future"] + p["other"] == len(fixes_with(traj, faults))
    assert first.unknown_clock > 0
    second = drive(study_filter(), imu, arrivals(fixes_with(traj, {}, seed=9), {})).estimate().health
    both = second.plus_paths(first.paths())
    assert both.paths() == {k: first.paths()[k] + second.paths()[k] for k in first.paths()}
    assert (both.status, both.pos_sigma_m, both.flagged_rsus) == (second.status, second.pos_sigma_m, second.flagged_rsus)
    assert second.plus_paths({}) is second


def test_a_camera_names_its_calibration():
    """Camera.calibration_id (what a fix states as Fix.calib_id): the same file gives the same id; a pose
    moved by 0.01 deg, or a new calibration date, another."""
    from toptag.camera import Camera, CameraFile
    from toptag.geometry import rodrigues

    path = "toptag/data/demo/rsu-sw.json"
    cam = Camera.load(path)
    assert cam.calibration_id == Camera.load(path).calibration_id and len(cam.calibration_id) == 12
    data = CameraFile.model_validate_json(open(path).read()).model_dump()
    turned = dict(data, R_wc=(rodrigues(np.array([0.0, 0.0, math.radians(0.01)])) @ np.asarray(data["R_wc"])).tolist())
    dated = dict(data, calibration={"date": "2026-11-23"})
    ids = {Camera.from_dict(d).calibration_id for d in (data, turned, dated)}
    assert len(ids) == 3, ids

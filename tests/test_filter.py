"""The bus filter (toptag/fusion/filter.py): delayed fixes at capture time, ordering independence,
admission (duplicates, too old, before start), chi-square gating that a starving filter cannot be
talked out of, honest degradation without fixes, start-up and re-acquisition."""
import math

import numpy as np
import pytest
from scipy.stats import chi2

from sim.motion import ImuModel, bus_trajectory
from sim.scene import rsu_mounts
from toptag.fix import Fix
from toptag.fusion.filter import BusFilter, FilterConfig
from toptag.fusion.outcomes import FixOutcome
from toptag.fusion.state import FusedState

pytestmark = pytest.mark.unit

MS = 1_000_000
RSUS = {m.id: m.position[:2] for m in rsu_mounts()}


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def make_fixes(traj, rng, rsus=("rsu-sw", "rsu-se", "rsu-ne"), rate_hz=10.0, t_from=0.0, t_to=None,
               sigma=0.04, yaw_sigma_deg=0.15, range_m=22.0, skip=None, clock_bound_ns=0):
    """Capture-stamped fixes with noise drawn from their reported covariance, from RSUs whose clocks
    are exact (bound 0) unless said otherwise."""
    t_to = traj.duration if t_to is None else t_to
    C = np.diag([sigma ** 2, sigma ** 2, math.radians(yaw_sigma_deg) ** 2])
    L = np.linalg.cholesky(C)
    out = []
    for j, rid in enumerate(rsus):
        t = np.arange(t_from + 0.1 * (j + 1) / (len(rsus) + 1) / rate_hz * 10, t_to, 1.0 / rate_hz)
        st = traj.state_at(t)
        for i, ti in enumerate(t):
            if np.hypot(st.x[i] - RSUS[rid][0], st.y[i] - RSUS[rid][1]) > range_m:
                continue
            if skip is not None and skip[0] <= ti < skip[1]:
                continue
            n = L @ rng.standard_normal(3)
            out.append(Fix(traj.t_ns(ti), st.x[i] + n[0], st.y[i] + n[1], _wrap(st.yaw[i] + n[2]), C, rid, i,
                           clock_bound_ns=clock_bound_ns))
    out.sort(key=lambda f: (f.t_ns, f.source))
    return out


def drive(flt, imu, arrivals, outputs_every=2, on_output=None, decide=True):
    """Feed IMU rows and (arrival_ns, fix) in time order; returns {fix key: outcome at arrival}."""
    arrivals = sorted(arrivals, key=lambda a: a[0])
    j = 0
    got = {}
    for k, (t_ns, g, ax, ay, w) in enumerate(imu.rows()):
        while j < len(arrivals) and arrivals[j][0] < t_ns:
            a, f = arrivals[j]
            got[(f.t_ns, f.source, f.seq)] = flt.add_fix(f, arrival_ns=a, decide=decide)
            j += 1
        flt.add_imu(t_ns, g, ax, ay, w)
        if on_output is not None and k % outputs_every == 0 and flt.initialized and t_ns >= flt.buffer_start_ns:
            on_output(t_ns, flt.estimate(t_ns))
    for a, f in arrivals[j:]:  # arriving after the last IMU sample
        got[(f.t_ns, f.source, f.seq)] = flt.add_fix(f, arrival_ns=a, decide=decide)
    return got


def pos_err(est: FusedState, traj):
    st = traj.state_at_ns(est.t_ns)
    return math.hypot(est.x - st.x, est.y - st.y)


def nees(est: FusedState, traj):
    st = traj.state_at_ns(est.t_ns)
    e = np.array([est.x - st.x, est.y - st.y, _wrap(est.yaw - st.yaw)])
    return float(e @ np.linalg.solve(est.cov, e))


@pytest.fixture(scope="module")
def left_turn():
    traj = bus_trajectory("left", "w", seed=1, start_dist=30.0, end_dist=25.0)  # ends inside RSU coverage
    imu = ImuModel().synthesize(traj, 0.0, traj.duration, np.random.default_rng(11))
    return traj, imu


# ----------------------------------------------------------------------------- ordering
def test_out_of_order_replay_equals_in_order(left_turn):
    traj, imu = left_turn
    fixes = make_fixes(traj, np.random.default_rng(2))
    spoof = fixes[40].replace(x=fixes[40].x + 5.0, seq=10_000, t_ns=fixes[40].t_ns + 3 * MS)
    fixes = fixes + [spoof]
    in_order = [(f.t_ns + 150 * MS, f) for f in fixes]
    rng = np.random.default_rng(3)
    shuffled = [(f.t_ns + int(rng.uniform(20, 600)) * MS, f) for f in fixes]  # heavy reordering
    assert any(a1[1].t_ns > a2[1].t_ns for a1, a2 in zip(sorted(shuffled, key=lambda a: a[0]),
                                                      sorted(shuffled, key=lambda a: a[0])[1:]))
    a, b = BusFilter(), BusFilter()
    # both start from the same first fix, delivered first
    drive(a, imu, in_order)
    first = min(fixes, key=lambda f: f.t_ns)
    shuffled = [(min(t for t, _ in shuffled) - 1, first)] + [s for s in shuffled if s[1] is not first]
    drive(b, imu, shuffled)
    ea, eb = a.estimate(), b.estimate()
    assert np.allclose(ea.state, eb.state, rtol=0, atol=1e-9)
    assert np.allclose(ea.state_cov, eb.state_cov, rtol=0, atol=1e-12)
    ca, cb = a.counters(), b.counters()
    for k in ("accepted", "rejected_gate", "initialized", "too_old", "duplicate"):
        assert ca[k] == cb[k], k
    assert ca["rejected_gate"] >= 1  # the spoof, in both orders
    assert pos_err(ea, traj) < 0.05


def test_fixes_decided_when_next_asked_give_the_same_estimates(left_turn):
    """add_fix(decide=False) leaves a buffered fix's decision to the next estimate, taken with the fixes added
    meanwhile (the steps after the oldest re-run once): every estimate, outcome and count as when each fix is
    decided on arrival, to the bit, out of order and with a spoof among them."""
    traj, imu = left_turn
    fixes = make_fixes(traj, np.random.default_rng(4))
    fixes.append(fixes[30].replace(x=fixes[30].x + 5.0, seq=10_000, t_ns=fixes[30].t_ns + 3 * MS))
    rng = np.random.default_rng(5)
    arrivals = [(f.t_ns + int(rng.uniform(20, 300)) * MS, f) for f in fixes]
    now, later, outs = BusFilter(), BusFilter(), ([], [])
    got = [drive(flt, imu, arrivals, outputs_every=3, on_output=lambda t, e, o=o: o.append(e), decide=decide)
           for flt, o, decide in ((now, outs[0], True), (later, outs[1], False))]
    assert len(outs[0]) == len(outs[1]) > 100
    for a, b in zip(*outs):
        assert np.array_equal(a.state, b.state) and np.array_equal(a.state_cov, b.state_cov), a.t_ns
        assert a.health == b.health
    assert now.counters() == later.counters() and now.fix_outcomes() == later.fix_outcomes()
    assert now.counters()["rejected_gate"] >= 1  # the spoof
    buffered = [k for k, o in got[0].items() if o not in (FixOutcome.INITIALIZED, FixOutcome.DUPLICATE)]
    assert {got[1][k] for k in buffered} == {FixOutcome.PENDING}
    assert FixOutcome.ACCEPTED in {got[0][k] for k in buffered}


def test_fix_applied_at_capture_time_not_arrival(left_turn):
    """The same fixes with 0 ms and 250 ms delay give the same estimate once all have arrived."""
    traj, imu = left_turn
    fixes = make_fixes(traj, np.random.default_rng(4), t_to=6.0)
    a, b = BusFilter(), BusFilter()
    drive(a, imu, [(f.t_ns, f) for f in fixes])
    drive(b, imu, [(f.t_ns + 250 * MS, f) for f in fixes])
    assert np.allclose(a.estimate().state, b.estimate().state, atol=1e-9)


# ----------------------------------------------------------------------------- admission
def test_duplicates_too_old_before_start_future_invalid_are_counted(left_turn):
    traj, imu = left_turn
    fixes = make_fixes(traj, np.random.default_rng(5), t_from=1.0, t_to=5.0)
    f = BusFilter(FilterConfig(buffer_s=1.0))
    rows = list(imu.rows())
    first = fixes[0]
    pre = [r for r in rows if r[0] < first.t_ns + 100 * MS]
    for r in pre:
        f.add_imu(*r)
    assert f.add_fix(first) is FixOutcome.INITIALIZED
    assert f.add_fix(first) is FixOutcome.DUPLICATE
    assert f.add_fix(first.replace(seq=first.seq + 99999)) is FixOutcome.DUPLICATE  # same source, same capture
    early = first.replace(t_ns=first.t_ns - 50 * MS, seq=-1)
    assert f.add_fix(early) is FixOutcome.BEFORE_START
    for r in rows[len(pre):]:
        if r[0] > first.t_ns + 2500 * MS:
            break
        f.add_imu(*r)
    head = f.head_ns
    assert head - f.buffer_start_ns >= 1_000 * MS  # the buffer covers at least 1 s
    old = fixes[5].replace(t_ns=head - 1200 * MS, seq=77777)
    assert f.add_fix(old) is FixOutcome.TOO_OLD
    fut = fixes[5].replace(t_ns=head + 2000 * MS, seq=88888)
    assert f.add_fix(fut) is FixOutcome.FUTURE
    bad = fixes[6].replace(cov=np.full((3, 3), np.nan), seq=99998)
    assert f.add_fix(bad) is FixOutcome.INVALID
    notpd = fixes[6].replace(cov=np.diag([1e-3, -1e-3, 1e-5]), seq=99997)
    assert f.add_fix(notpd) is FixOutcome.INVALID
    ok = fixes[10].replace(t_ns=head - 300 * MS, seq=55555)
    st = traj.state_at_ns(ok.t_ns)
    ok = ok.replace(x=st.x, y=st.y, yaw=st.yaw)
    assert f.add_fix(ok) is FixOutcome.ACCEPTED
    again = ok.replace()  # a re-sent copy
    assert f.add_fix(again) is FixOutcome.DUPLICATE
    c = f.counters()
    assert c["initialized"] == 1 and c["duplicate"] == 3 and c["before_start"] == 1
    assert c["too_old"] == 1 and c["future"] == 1 and c["invalid"] == 2 and c["accepted"] == 1
    assert c["per_source"][first.source]["duplicate"] >= 1


def test_several_rsus_each_counted(left_turn):
    traj, imu = left_turn
    rsus = ("rsu-sw", "rsu-se", "rsu-ne", "rsu-nw")
    fixes = make_fixes(traj, np.random.default_rng(6), rsus=rsus)
    f = BusFilter()
    drive(f, imu, [(x.t_ns + 120 * MS, x) for x in fixes])
    c = f.counters()
    assert set(c["per_source"]) == set(rsus)
    assert sum(d.get("accepted", 0) + d.get("initialized", 0) for d in c["per_source"].values()) == \
        c["accepted"] + c["initialized"]
    assert c["fixes"] == len(fixes)
    assert c["rejected_gate"] <= 3  # 0.1 % false rejections expected on consistent fixes


# ----------------------------------------------------------------------------- gating
def test_spoofed_fix_5m_off_is_rejected_and_changes_nothing(left_turn):
    traj, imu = left_turn
    fixes = make_fixes(traj, np.random.default_rng(7), t_to=6.0)
    target = fixes[len(fixes) // 2]
    spoof = target.replace(x=target.x + 3.0, y=target.y - 4.0, seq=123456, t_ns=target.t_ns + 7 * MS,
                           source="rsu-evil")
    a, b = BusFilter(), BusFilter()
    drive(a, imu, [(f.t_ns + 100 * MS, f) for f in fixes])
    got = drive(b, imu, [(f.t_ns + 100 * MS, f) for f in fixes + [spoof]])
    assert got[(spoof.t_ns, spoof.source, spoof.seq)] is FixOutcome.REJECTED_GATE
    assert b.counters()["rejected_gate"] == a.counters()["rejected_gate"] + 1
    assert b.counters()["per_source"]["rsu-evil"] == {"rejected_gate": 1}
    assert np.array_equal(a.estimate().state, b.estimate().state)
    assert b.estimate().health.rejected >= 1


def _long_straight(seconds=32.0):
    return bus_trajectory("straight", "w", start_dist=10.0, end_dist=seconds * 8.4, seed=3)


def test_wild_fix_still_rejected_after_a_long_run_of_rejections():
    """30 s of wild fixes only: every one rejected, the filter's own covariance grows past the point
    where an uncapped gate would let a 5 m fix in, and the 5 m fix is still rejected."""
    traj = _long_straight()
    # a calibrated gyro (the dead reckoning stays within ~1 m) but a pessimistic odometry model, so
    # the filter's own covariance grows fast
    imu = ImuModel(gyro_bias_sigma=0.0, gyro_bias_walk=0.0).synthesize(traj, 0.0, 31.0, np.random.default_rng(8))
    rng = np.random.default_rng(9)
    cfg = FilterConfig(pos_noise_density=0.5, gyro_bias_sigma0=1e-5, gyro_bias_walk=1e-7)
    flt = BusFilter(cfg)
    st0 = traj.state_at(0.0)
    flt.initialize(traj.t0_ns, st0.x, st0.y, st0.yaw, pos_sigma=0.05, yaw_sigma=0.01, speed=st0.speed,
                   trusted=True)
    wild, seq = [], 0
    for t in np.arange(0.5, 30.0, 0.1):  # wild fixes from two RSUs, 3-10 m off in random directions
        st = traj.state_at(t)
        for src in ("rsu-a", "rsu-b"):
            r, phi = rng.uniform(3.0, 10.0), rng.uniform(0, 2 * np.pi)
            wild.append(Fix(traj.t_ns(t + 0.013 * (src == "rsu-b")), st.x + r * np.cos(phi),
                                st.y + r * np.sin(phi), st.yaw + rng.normal(0, 0.3),
                                np.diag([0.04 ** 2, 0.04 ** 2, 0.003 ** 2]), src, seq))
            seq += 1
    drive(flt, imu, [(f.t_ns + 80 * MS, f) for f in wild])
    c = flt.counters()
    assert c["rejected_gate"] == len(wild) and c["reacquired"] == 0 and c["accepted"] == 0
    est = flt.estimate()
    assert est.health.consecutive_rejections == len(wild)
    assert est.health.status in ("degraded", "lost")
    assert est.health.pos_sigma_m > 2.0  # honest growth: an uncapped gate would now pass 5 m
    st = traj.state_at_ns(est.t_ns)
    err = math.hypot(est.x - st.x, est.y - st.y)
    assert err < 3 * est.health.pos_sigma_m  # the covariance covers the dead-reckoning drift
    t5 = est.t_ns - 50 * MS
    s5 = traj.state_at_ns(t5)
    five = Fix(t5, s5.x, s5.y + 5.0, s5.yaw, np.diag([0.04 ** 2, 0.04 ** 2, 0.003 ** 2]), "rsu-c", 1)
    S_uncapped = est.cov + five.cov
    nu = np.array([0.0, 5.0, 0.0])
    assert nu @ np.linalg.solve(S_uncapped, nu) < cfg.gate_threshold  # what the cap protects against
    assert flt.add_fix(five) is FixOutcome.REJECTED_GATE


def test_reacquires_with_a_consensus_of_true_fixes_after_drift(left_turn):
    """Started (trusted) 2.5 m off: true fixes are rejected by the capped gate at first, then agree
    with each other from several RSUs and the filter re-acquires."""
    traj, imu = left_turn
    fixes = make_fixes(traj, np.random.default_rng(12), t_from=1.5)
    f = BusFilter()
    st = traj.state_at(1.0)
    rows = list(imu.rows())
    k0 = next(i for i, r in enumerate(rows) if r[0] >= traj.t_ns(1.0))
    f.initialize(rows[k0][0], st.x + 1.5, st.y - 2.0, st.yaw, pos_sigma=0.05, yaw_sigma=0.005, speed=st.speed,
                 trusted=True)
    errs = []
    drive(f, imu, [(x.t_ns + 150 * MS, x) for x in fixes], on_output=lambda t, e: errs.append((t, e)))
    c = f.counters()
    assert c["reacquired"] >= 1 and c["rejected_gate"] >= 4
    tail = [pos_err(e, traj) for t, e in errs if t > traj.t_ns(4.5)]
    assert max(tail) < 0.1
    assert errs[-1][1].health.status == "ok"


# ----------------------------------------------------------------------------- outage
def test_three_second_outage_degrades_honestly_and_recovers():
    traj = bus_trajectory("left", "w", seed=2)
    t_gap = (3.0, 6.0)  # the whole turn without fixes
    runs = 12
    before, during_end, after, nees_gap = [], [], [], []
    status_gap, status_after = set(), set()
    for r in range(runs):
        imu = ImuModel().synthesize(traj, 0.0, traj.duration, np.random.default_rng(100 + r))
        fixes = make_fixes(traj, np.random.default_rng(200 + r), skip=t_gap)
        f = BusFilter()
        log = []
        drive(f, imu, [(x.t_ns + 200 * MS, x) for x in fixes], on_output=lambda t, e: log.append(e))
        ts = np.array([traj.seconds(e.t_ns) for e in log])

        def at(t):
            return log[int(np.argmin(np.abs(ts - t)))]
        before.append(at(2.9).health.pos_sigma_m)
        # fixes captured before t_gap[0] arrive 200 ms late: the outage is felt from ~3.2 s
        end = at(t_gap[1] + 0.15)
        during_end.append(end.health.pos_sigma_m)
        nees_gap.append(np.mean([nees(e, traj) for e in log if t_gap[0] + 0.5 < traj.seconds(e.t_ns) < t_gap[1] + 0.2]))
        status_gap.add(end.health.status)
        assert end.health.since_last_fix_s > 2.5
        assert pos_err(end, traj) < 0.5
        rec = at(t_gap[1] + 1.5)
        after.append(rec.health.pos_sigma_m)
        status_after.add(rec.health.status)
        assert pos_err(rec, traj) < 0.06
        assert rec.health.since_last_fix_s < 0.5
    before, during_end, after = map(np.array, (before, during_end, after))
    # the covariance grows during the outage (before it, the RSUs' time offsets already widen it along
    # the track: a single RSU's offset is confounded with the position there) ...
    assert np.all(during_end > 1.5 * before) and np.all(during_end > before + 0.03)
    assert np.all(after < 1.5 * before)  # ... and shrinks back once fixes return
    assert status_gap == {"degraded"} and status_after == {"ok"}
    lo, hi = chi2.ppf([0.005, 0.995], 3 * runs) / runs
    assert lo < np.mean(nees_gap) < hi, (np.mean(nees_gap), lo, hi)  # honest: errors match the covariance


# ----------------------------------------------------------------------------- start-up
def test_startup_from_coarse_prior_ignores_a_lone_spoof(left_turn):
    traj, imu = left_turn
    fixes = make_fixes(traj, np.random.default_rng(13), t_from=1.0)
    st = traj.state_at(0.5)
    f = BusFilter()
    rows = list(imu.rows())
    k0 = next(i for i, r in enumerate(rows) if r[0] >= traj.t_ns(0.5))
    for r in rows[:k0]:
        f.add_imu(*r)
    f.initialize(rows[k0][0], st.x + 2.0, st.y - 1.5, st.yaw + 0.2, pos_sigma=4.0, yaw_sigma=0.5)
    assert f.estimate().health.status == "acquiring"
    s1 = traj.state_at_ns(fixes[0].t_ns - 5 * MS)
    spoof = Fix(fixes[0].t_ns - 5 * MS, s1.x - 4.0, s1.y + 3.0, s1.yaw, fixes[0].cov, "rsu-evil", 0)
    out = drive(f, imu, [(spoof.t_ns + 100 * MS, spoof)] + [(x.t_ns + 100 * MS, x) for x in fixes])
    assert out[(spoof.t_ns, "rsu-evil", 0)] is FixOutcome.UNCONFIRMED
    assert f.fix_outcomes()[0][1] is not FixOutcome.ACCEPTED or f.fix_outcomes()[0][0][1] != "rsu-evil"
    est = f.estimate()
    assert est.health.status == "ok"
    assert pos_err(est, traj) < 0.05
    assert f.counters()["accepted"] >= len(fixes) - 5


def test_startup_from_first_confident_fix(left_turn):
    traj, imu = left_turn
    fixes = make_fixes(traj, np.random.default_rng(14), t_from=1.0)
    f = BusFilter()
    assert f.estimate() is None
    coarse = fixes[0].replace(cov=np.diag([2.0 ** 2, 2.0 ** 2, 0.3 ** 2]), seq=-5, t_ns=fixes[0].t_ns - MS)
    rows = list(imu.rows())
    arrivals = [(coarse.t_ns + 150 * MS, coarse)] + [(x.t_ns + 150 * MS, x) for x in fixes]
    got = drive(f, imu, arrivals)
    assert got[(coarse.t_ns, coarse.source, coarse.seq)] is FixOutcome.NOT_INITIALIZED
    assert got[(fixes[0].t_ns, fixes[0].source, fixes[0].seq)] is FixOutcome.INITIALIZED
    c = f.counters()
    assert c["initialized"] == 1 and c["not_initialized"] == 1
    # fixes captured before the starting fix but arriving after it are "before_start"
    assert c["before_start"] == 0 or c["before_start"] < 3
    est = f.estimate(rows[-1][0] + 10 * MS)  # 10 ms beyond the newest sample: predicted
    assert est.health.extrapolated_s == pytest.approx(0.01)
    assert pos_err(est, traj) < 0.05 and est.health.status == "ok"
    assert abs(est.speed - traj.state_at_ns(est.t_ns).speed) < 0.05


def test_estimate_inside_the_buffer_and_health_fields(left_turn):
    traj, imu = left_turn
    fixes = make_fixes(traj, np.random.default_rng(15), t_to=5.0)
    f = BusFilter()
    drive(f, imu, [(x.t_ns + 200 * MS, x) for x in fixes if traj.seconds(x.t_ns) < 4.0])
    head = f.head_ns
    past = f.estimate(head - 505 * MS)
    assert past.t_ns == head - 505 * MS and past.health.extrapolated_s == 0.0
    assert pos_err(past, traj) < 0.05
    h = f.estimate().health
    assert h.last_fix_delay_s == pytest.approx(0.2, abs=1e-9)
    assert h.last_fix_source in RSUS
    d = f.estimate().to_dict()
    assert {"x", "y", "yaw", "cov", "health"} <= set(d) and "since_last_fix_s" in d["health"]
    with pytest.raises(ValueError):
        f.estimate(f.buffer_start_ns - 1)


def test_fixes_without_sequence_numbers(left_turn):
    traj, imu = left_turn
    fixes = [f.replace(seq=None) for f in make_fixes(traj, np.random.default_rng(16), t_to=4.0)]
    flt = BusFilter()
    rows = [r for r in imu.rows() if r[0] <= traj.t_ns(4.2)]
    j = 0
    for r in rows:
        while j < len(fixes) and fixes[j].t_ns + 100 * MS < r[0]:
            flt.add_fix(fixes[j], arrival_ns=fixes[j].t_ns + 100 * MS)
            j += 1
        flt.add_imu(*r)
    c = flt.counters()
    assert c["duplicate"] == 0 and c["accepted"] + c["initialized"] == j
    assert flt.add_fix(fixes[j - 1].replace()) is FixOutcome.DUPLICATE  # same source, same capture time
    assert set(c["per_source"]) == {"rsu-sw", "rsu-se", "rsu-ne"} & set(c["per_source"])


def test_the_filter_takes_only_core_fixes():
    with pytest.raises(TypeError, match="toptag.fix.Fix"):
        BusFilter().add_fix({"t_ns": 1, "x": 0.0, "y": 0.0, "yaw": 0.0, "cov": np.eye(3).tolist()})


def test_fusion_study_writes_results_in_the_agreed_shape(tmp_path):
    from sim.studies import fusion

    res = fusion.run(tmp_path, [0, 200], jitter_ms=30, seed=1, runs=2, plots=False, log=lambda *_: None,
                     progress=False)
    saved = __import__("json").loads((tmp_path / "results.json").read_text())
    for key in ("0", "200"):
        r = saved["latency_ms"][key]
        for k in ("fused_pos_rms_m", "naive_pos_rms_m", "dead_reckoning_pos_rms_m", "nees_mean"):
            assert math.isfinite(r[k])
    r0, r2 = res["latency_ms"]["0"], res["latency_ms"]["200"]
    assert r2["fused_pos_rms_m"] < 0.05 and r2["naive_pos_rms_m"] > 10 * r2["fused_pos_rms_m"]
    assert r2["fused_pos_rms_m"] <= 1.3 * r0["fused_pos_rms_m"]
    assert fusion.main(["--out", str(tmp_path / "x"), "--latency-ms", "a,b"]) == 2


def test_wire_messages_in_and_out(left_turn):
    """Wire PoseFix -> protocol.convert -> filter -> protocol.convert -> wire FusedPose."""
    from protocol import messages
    from protocol.convert import fix_from_message, fix_to_message, fused_to_message

    traj, imu = left_turn
    fixes = make_fixes(traj, np.random.default_rng(17), t_to=3.0)
    flt = BusFilter()
    rows = [r for r in imu.rows() if r[0] <= traj.t_ns(3.2)]
    j = applied = 0
    for r in rows:
        while j < len(fixes) and fixes[j].t_ns + 120 * MS < r[0]:
            f = fixes[j].replace(z=3.0, method="s_opt", tags=(3,), rms_px=0.4)
            msg = fix_to_message(f, "bus-17", "x1", publish_time_ns=f.t_ns + 50 * MS)
            assert isinstance(msg, messages.PoseFix) and msg.rsu_id == f.source and msg.frame_seq == f.seq
            applied += flt.add_fix(fix_from_message(msg, arrival_ns=f.t_ns + 120 * MS)).applied
            j += 1
        flt.add_imu(*r)
    est = flt.estimate(rows[-1][0] + 5 * MS)
    out = fused_to_message(est, "bus-17")
    assert isinstance(out, messages.FusedPose) and out.bus_id == "bus-17" and out.t_ns == est.t_ns
    assert out.health.accepted_fixes == applied >= j - 2 and out.health.last_fix_delay_ns == 120 * MS
    assert out.health.last_fix_rsu in RSUS and 0 < out.health.since_last_fix_ns < 400 * MS
    assert pos_err(est, traj) < 0.05


# ----------------------------------------------------------------------------- biased cameras, starved IMU
def test_biased_cameras_leave_the_filter_consistent(tmp_path):
    """Cameras standing off their surveyed poses by their stated calibration (0.05 deg / 2 cm per axis, the
    image model's) give every fix of an RSU the same bias, and each fix says how large it may be
    (Fix.calib_cov). Taken as white noise it averages down with every fix and the fused track claims far
    more than it knows (NEES ~12 on the 3-dof pose); carried as each RSU's bias (the default, Schmidt
    "consider" states) the NEES is back in its band, and the track no worse."""
    from sim.studies.fusion import STUDY_DRIFT_THRESHOLDS, FixErrorModel, run

    model = FixErrorModel(calib_rot_sigma_deg=0.05, calib_trans_sigma=0.02)
    res = {}
    for mode in ("noise", "consider"):
        cfg = FilterConfig(**STUDY_DRIFT_THRESHOLDS, calib_bias=mode)
        r = run(tmp_path / mode, (100,), runs=4, fix_model=model, config=cfg, plots=False, progress=False,
                log=lambda *a: None)
        res[mode] = r["latency_ms"]["100"]
    lo, hi = res["consider"]["nees_band_95"]
    assert res["consider"]["nees_mean"] <= hi, res
    assert res["noise"]["nees_mean"] > 2 * res["consider"]["nees_mean"], res
    assert res["consider"]["fused_pos_rms_m"] <= 1.02 * res["noise"]["fused_pos_rms_m"], res


def test_an_estimate_beyond_the_newest_imu_sample_claims_no_more_than_it_knows():
    """On a starved machine the IMU lags and a bus agent's estimate of now is a prediction past the newest
    sample, where nothing measures the yaw rate or the acceleration. Its covariance must say so: 0.5 s
    ahead through turns, starts and stops, the 3-dof NEES stays at or below 3 (held constant without the
    growth, the poses claimed 1.4 cm and were 8 cm RMS, up to 48 cm, off: NEES 54), and poses claiming
    5 cm or better are within it."""
    from sim.studies.fusion import FixErrorModel, simulate_fixes

    nees, confident = [], []
    for route in ("left", "stop"):
        traj = bus_trajectory(route, "w", seed=0)
        rng = np.random.default_rng(3)
        imu = ImuModel().synthesize(traj, 0.0, traj.duration, rng)
        fixes = simulate_fixes(traj, FixErrorModel(), 4, rng)
        flt = BusFilter(FilterConfig())

        def ahead(t_ns, _):
            t = t_ns + 500 * MS
            if t > traj.t_ns(traj.duration) or t_ns < traj.t0_ns + 3 * 10**9:
                return
            e = flt.estimate(t)
            st = traj.state_at_ns(t)
            d = np.array([e.x - st.x, e.y - st.y, _wrap(e.yaw - st.yaw)])
            nees.append(float(d @ np.linalg.solve(e.cov, d)))
            if max(e.cov[0, 0], e.cov[1, 1]) <= 0.05 ** 2:
                confident.append(math.hypot(d[0], d[1]))
        drive(flt, imu, [(f.t_ns, f) for f in fixes], outputs_every=20, on_output=ahead)
    assert len(nees) > 50
    assert np.mean(nees) <= 3.0, np.mean(nees)
    assert not confident or math.sqrt(np.mean(np.square(confident))) <= 0.08

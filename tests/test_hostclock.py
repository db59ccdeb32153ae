"""The host clock probe (toptag/hostclock.py): chrony's and linuxptp's real output formats, and the
"system" fallback on a host that runs neither, for real.

The samples below are in the exact formats the tools print (field names, alignment, units), with
numbers of our own. Formats recorded from: chronyc(1) "tracking" (chrony 4.x manual, which also gives
the accuracy bound |System time| + Root dispersion + Root delay / 2) and published `chronyc tracking`
outputs of an NTP client, a PPS-disciplined stratum-1 server and a PHC (PTP hardware clock) reference;
linuxptp's `pmc -u -b 0 'GET TIME_STATUS_NP'` as printed by pmc (pmc_common.c) and shown in the
NVIDIA Cumulus Linux PTP documentation."""
import shutil

import pytest

from protocol.convert import clock_to_message
from toptag.hostclock import (
    PHC2SYS_MARGIN_NS,
    SYSTEM,
    HostClock,
    HostClockProbe,
    parse_chronyc_tracking,
    parse_pmc_time_status,
    probe,
)

pytestmark = pytest.mark.unit

CHRONY_NTP = """Reference ID    : C0A80A1B (10.10.27.50)
Stratum         : 3
Ref time (UTC)  : Sun Mar 12 20:22:02 2023
System time     : 0.000072261 seconds fast of NTP time
Last offset     : +0.000203388 seconds
RMS offset      : 0.000159382 seconds
Frequency       : 20.877 ppm slow
Residual freq   : +0.027 ppm
Skew            : 0.583 ppm
Root delay      : 0.001047121 seconds
Root dispersion : 0.020145597 seconds
Update interval : 521.0 seconds
Leap status     : Normal
"""

CHRONY_PPS = """Reference ID    : 50505300 (PPS)
Stratum         : 1
Ref time (UTC)  : Sat Dec 21 17:18:57 2024
System time     : 0.000000106 seconds slow of NTP time
Last offset     : -0.000000096 seconds
RMS offset      : 0.000000172 seconds
Frequency       : 0.569 ppm fast
Residual freq   : -0.000 ppm
Skew            : 0.005 ppm
Root delay      : 0.000000001 seconds
Root dispersion : 0.000017795 seconds
Update interval : 16.0 seconds
Leap status     : Normal
"""

CHRONY_PHC = CHRONY_PPS.replace("50505300 (PPS)", "50484330 (PHC0)")

CHRONY_UNSYNCED = """Reference ID    : 00000000 ()
Stratum         : 0
Ref time (UTC)  : Thu Jan 01 00:00:00 1970
System time     : 0.000000000 seconds slow of NTP time
Last offset     : +0.000000000 seconds
RMS offset      : 0.000000000 seconds
Frequency       : 20.837 ppm slow
Residual freq   : +0.000 ppm
Skew            : 0.000 ppm
Root delay      : 1.000000000 seconds
Root dispersion : 1.000000000 seconds
Update interval : 0.0 seconds
Leap status     : Not synchronised
"""

CHRONY_LOCAL = CHRONY_NTP.replace("C0A80A1B (10.10.27.50)", "7F7F0101 ()")

PMC_SLAVE = """sending: GET TIME_STATUS_NP
	7cfe90.fffe.f56dfc-0 seq 0 RESPONSE MANAGEMENT TIME_STATUS_NP
		master_offset              -12610
		ingress_time               1525717806521177336
		cumulativeScaledRateOffset +0.000000000
		scaledLastGmPhaseChange    0
		gmTimeBaseIndicator        0
		lastGmPhaseChange          0x0000'0000000000000000.0000
		gmPresent                  true
		gmIdentity                 000200.fffe.000005
"""

PMC_NO_GRANDMASTER = PMC_SLAVE.replace("gmPresent                  true", "gmPresent                  false")


def test_chrony_following_an_ntp_server():
    c = parse_chronyc_tracking(CHRONY_NTP)
    assert c.source == "ntp"
    # |system time| + root dispersion + root delay / 2
    assert c.bound_ns == round((0.000072261 + 0.020145597 + 0.001047121 / 2) * 1e9)
    assert "10.10.27.50" in c.detail and "stratum 3" in c.detail


def test_chrony_on_pps_is_gnss_and_on_a_ptp_hardware_clock_is_ptp():
    pps, phc = parse_chronyc_tracking(CHRONY_PPS), parse_chronyc_tracking(CHRONY_PHC)
    assert pps.source == "gnss" and phc.source == "ptp"
    assert pps.bound_ns == phc.bound_ns == round((0.000000106 + 0.000017795 + 0.000000001 / 2) * 1e9)


@pytest.mark.parametrize("text", [CHRONY_UNSYNCED, CHRONY_LOCAL, "", "506 Cannot talk to daemon\n",
                                  CHRONY_NTP.replace("Root delay      : 0.001047121 seconds\n", "")])
def test_chrony_unsynchronised_local_or_unreadable_is_no_answer(text):
    assert parse_chronyc_tracking(text) is None


def test_pmc_with_a_grandmaster_is_ptp_with_the_measured_offset():
    c = parse_pmc_time_status(PMC_SLAVE)
    assert c.source == "ptp" and c.bound_ns == 12610 + PHC2SYS_MARGIN_NS
    assert "000200.fffe.000005" in c.detail


@pytest.mark.parametrize("text", [PMC_NO_GRANDMASTER, "sending: GET TIME_STATUS_NP\n", "",
                                  PMC_SLAVE.replace("-12610", "n/a")])
def test_pmc_without_a_grandmaster_or_unreadable_is_no_answer(text):
    assert parse_pmc_time_status(text) is None


def test_system_fallback_for_real_when_neither_tool_runs(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))  # no chronyc, no pmc on this PATH
    assert probe() == SYSTEM and SYSTEM.bound_ns is None and not SYSTEM.known
    info = clock_to_message(probe())
    assert info.source == "system" and info.sync_uncertainty_ns is None


def test_this_hosts_clock():
    """This machine as it is: neither tool here gives "system"; a host with chrony or ptp4l gives a
    disciplined source with a bound."""
    c = probe()
    if shutil.which("chronyc") is None and shutil.which("pmc") is None:
        assert c == SYSTEM
    else:
        assert c == SYSTEM or (c.source in ("ntp", "ptp", "gnss") and c.bound_ns >= 0)
    p = HostClockProbe(period_s=0.05).start()
    try:
        assert isinstance(p.current(), HostClock) and p.current().source == c.source
    finally:
        p.close()

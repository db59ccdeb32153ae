"""How this host's clock is disciplined: the source of its time and a bound on its offset.

Every service stamps with the host's clock (an RSU its camera frames, a bus its announcements), so a
receiver needs to know how far those stamps can be trusted. The probe asks, in this order:

1. chrony (`chronyc -n tracking`): synchronised when "Leap status" is not "Not synchronised" and the
   reference is not the local clock. The bound is chrony's own (chronyc(1), "tracking"):
   |System time| + Root dispersion + Root delay / 2. The source is "ptp" when chrony follows a PTP
   hardware clock (reference PHC*), "gnss" for a PPS/GPS/NMEA reference clock, "ntp" otherwise.
2. linuxptp (`pmc -u -b 0 "GET TIME_STATUS_NP"`): with a grandmaster present, "ptp" and the port's
   last measured offset from it (master_offset, ns), plus `PHC2SYS_MARGIN_NS` for the system
   clock's tracking of the PTP hardware clock (phc2sys), which pmc does not report.
3. Otherwise "system" with no bound: nothing is known to discipline this clock.

A tool that is missing, fails, times out or prints something unexpected counts as absent. The
parsers are plain functions of the tools' text (tested on recorded outputs); `probe()` runs them;
`HostClockProbe` keeps the answer fresh from a background thread for a service.
"""
from __future__ import annotations

import logging
import re
import shutil
import subprocess
import threading
from dataclasses import dataclass

from toptag.units import ns_from_s

log = logging.getLogger(__name__)

PHC2SYS_MARGIN_NS = 1_000  # assumed accuracy of phc2sys (system clock to the PTP hardware clock)
PROBE_TIMEOUT_S = 2.0
CHRONYC = ("chronyc", "-n", "tracking")
PMC = ("pmc", "-u", "-b", "0", "GET TIME_STATUS_NP")


@dataclass(frozen=True)
class HostClock:
    """source: "system" | "ntp" | "ptp" | "gnss" (protocol.messages.ClockSource); bound_ns: a bound on
    |host clock - reference| (None: unknown); detail: what the probe saw, one line."""
    source: str = "system"
    bound_ns: int | None = None
    detail: str = "no clock discipline found (chrony, ptp4l)"

    @property
    def known(self) -> bool:
        return self.bound_ns is not None


SYSTEM = HostClock()


def _fields(text: str) -> dict[str, str]:
    out = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            out[key.strip().lower()] = value.strip()
    return out


def _seconds(value: str) -> float | None:
    m = re.match(r"([+-]?\d+(?:\.\d+)?(?:[eE][+-]?\d+)?)\s+seconds?", value)
    return float(m.group(1)) if m else None


def parse_chronyc_tracking(text: str) -> HostClock | None:
    """The clock `chronyc tracking` describes, or None when chrony is not synchronised (or the text is
    not chronyc's)."""
    f = _fields(text)
    ref, leap = f.get("reference id", ""), f.get("leap status", "")
    if not ref or not leap or leap.lower().startswith("not synchron"):
        return None
    system = f.get("system time", "")
    m = re.match(r"(\d+(?:\.\d+)?)\s+seconds?\s+(slow|fast)", system)
    delay, dispersion = _seconds(f.get("root delay", "")), _seconds(f.get("root dispersion", ""))
    if m is None or delay is None or dispersion is None:
        return None
    name = ref[ref.find("(") + 1:ref.rfind(")")] if "(" in ref else ""
    ref_id = ref.split()[0].upper()
    if ref_id in ("7F7F0101", "00000000") or name.upper() == "LOCAL":  # chrony's local (free-running) mode
        return None
    upper = name.upper()
    source = "ptp" if upper.startswith("PHC") else "gnss" if upper.startswith(("PPS", "GPS", "NMEA", "GNSS")) else "ntp"
    bound_s = float(m.group(1)) + dispersion + delay / 2.0
    stratum = f.get("stratum", "?")
    return HostClock(source, ns_from_s(bound_s),
                     f"chrony: reference {name or ref_id}, stratum {stratum}, system time {m.group(1)} s {m.group(2)}, "
                     f"bound {bound_s * 1e3:.3f} ms")


def parse_pmc_time_status(text: str) -> HostClock | None:
    """The clock `pmc "GET TIME_STATUS_NP"` describes (its first response: this host's ptp4l), or None
    without a grandmaster (or when the text is not pmc's)."""
    block = text.split("RESPONSE MANAGEMENT TIME_STATUS_NP", 1)
    if len(block) < 2:
        return None
    body = block[1].split("RESPONSE MANAGEMENT", 1)[0]
    values = {}
    for line in body.splitlines():
        parts = line.split()
        if len(parts) >= 2:
            values[parts[0]] = parts[1]
    if values.get("gmPresent") != "true" or "master_offset" not in values:
        return None
    try:
        offset = abs(int(values["master_offset"]))
    except ValueError:
        return None
    return HostClock("ptp", offset + PHC2SYS_MARGIN_NS,
                     f"ptp4l: grandmaster {values.get('gmIdentity', '?')}, master_offset {offset} ns "
                     f"(+{PHC2SYS_MARGIN_NS} ns assumed for phc2sys)")


def _run(cmd: tuple[str, ...]) -> str | None:
    if shutil.which(cmd[0]) is None:
        return None
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S, check=False)
    except (OSError, subprocess.SubprocessError) as e:
        log.debug("%s: %s", cmd[0], e)
        return None
    return p.stdout if p.returncode == 0 else None


def probe() -> HostClock:
    """This host's clock now (see the module docstring)."""
    for cmd, parse in ((CHRONYC, parse_chronyc_tracking), (PMC, parse_pmc_time_status)):
        text = _run(cmd)
        found = parse(text) if text else None
        if found is not None:
            return found
    return SYSTEM


class HostClockProbe:
    """The host's clock for a service, probed at once and then every `period_s` on a daemon thread."""

    def __init__(self, period_s: float = 60.0, probe_fn=probe):
        self._probe, self.period_s = probe_fn, period_s
        self._current = probe_fn()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        log.info("host clock: %s%s", self._current.source,
                 "" if self._current.bound_ns is None else f" (bound {self._current.bound_ns} ns)")

    def current(self) -> HostClock:
        return self._current

    def start(self) -> HostClockProbe:
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="host-clock", daemon=True)
            self._thread.start()
        return self

    def _loop(self) -> None:
        while not self._stop.wait(self.period_s):
            now = self._probe()
            if now != self._current:
                log.info("host clock now: %s (%s)", now.source, now.detail)
            self._current = now

    def close(self) -> None:
        self._stop.set()


__all__ = ["HostClock", "HostClockProbe", "SYSTEM", "parse_chronyc_tracking", "parse_pmc_time_status", "probe"]

"""The progress bar of every long job (the studies, the benchmarks, the demo): one look, on stderr, so
that stdout stays the job's result."""
from __future__ import annotations

import math
import sys
import time


class Progress:
    """A plain progress bar on stderr (redrawn in place on a terminal, a line per 10 % otherwise).

    bar = Progress(len(tasks), "toptag eval paper")
    for t in tasks:
        ...
        bar.update(note=t.name)
    bar.close()"""

    def __init__(self, total: float, label: str = "", stream=None, width: int = 30, unit: str = ""):
        self.total, self.label, self.width, self.unit = max(total, 1), label, width, unit
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.n, self.t0, self._last, self._decile = 0, time.monotonic(), 0.0, -1
        self._draw(force=True)

    def update(self, n: float = 1, note: str = "") -> None:
        """``n`` more done."""
        self.n += n
        self._draw(note=note)

    def set(self, n: float, note: str = "") -> None:
        """``n`` done in all (a job measured in seconds: the time it has run)."""
        self.n = n
        self._draw(note=note)

    def _draw(self, force: bool = False, note: str = "") -> None:
        now = time.monotonic()
        done = self.n >= self.total
        frac = min(self.n / self.total, 1.0)
        if self.tty:
            if not (force or done or now - self._last >= 0.2):
                return
        else:
            decile = int(frac * 10)
            if not (force or done or decile > self._decile):
                return
            self._decile = decile
        self._last = now
        el = now - self.t0
        eta = el / frac - el if frac > 0 else math.nan
        bar = "#" * int(frac * self.width) + "-" * (self.width - int(frac * self.width))
        count = f"{self.n:g}/{self.total:g}{self.unit}"
        text = (f"{self.label} [{bar}] {count} {frac:4.0%} {_clock(el)} elapsed"
                + (f", ETA {_clock(eta)}" if not done and math.isfinite(eta) else "") + (f"  {note}" if note else ""))
        self.stream.write(("\r" + text + "\033[K") if self.tty else text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


def _clock(s: float) -> str:
    s = int(round(s))
    return f"{s // 60}:{s % 60:02d}"

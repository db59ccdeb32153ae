"""Which intersection a bus is in, from its position: enter inside the approach radius, leave beyond the
radius plus a margin (hysteresis, so a noisy position at the edge does not flap)."""
from __future__ import annotations

from toptag.site import IntersectionSpec, MapFile


class IntersectionPresence:
    def __init__(self, map_file: MapFile):
        self.map = map_file
        self.current: IntersectionSpec | None = None

    def update(self, x: float, y: float) -> list[tuple[str, IntersectionSpec]]:
        """Feed a position; returns the transitions it caused, e.g. [("leave", a), ("enter", b)]."""
        events: list[tuple[str, IntersectionSpec]] = []
        if self.current is not None:
            cx, cy = self.current.center
            if ((x - cx) ** 2 + (y - cy) ** 2) ** 0.5 > self.current.radius + self.current.leave_margin:
                events.append(("leave", self.current))
                self.current = None
        if self.current is None:
            nearest, d = self.map.nearest(x, y)
            if d <= nearest.radius:
                self.current = nearest
                events.append(("enter", nearest))
        return events

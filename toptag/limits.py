"""The physical limits of the buses toptag tracks, in one place: the RSU's search regions, the
simulator's routes and the studies all assume the same bus."""
from __future__ import annotations

from toptag.units import mps_from_kmh

BUS_MAX_SPEED_MPS = mps_from_kmh(30.0)  # buses cross the intersection at up to 30 km/h
BUS_MAX_DECEL_MPS2 = 3.0  # emergency braking of a city bus
BUS_MAX_YAW_RATE = 0.6  # rad/s: a tight turn at low speed

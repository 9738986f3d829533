"""Synthetic airborne terrains with known ground, for the ground filter's tests.

Each scene is single-return airborne data as in the ISPRS filter test (Sithole & Vosselman 2004):
points uniformly at random in XY at a given mean spacing, one elevation each, the truth a boolean
``is_ground``. The scenes follow the test's difficult cases: a ramp up to a raised level, a bridge
over a cutting (the deck is an object where it spans the gap, ground where it rests on the
embankments), a steep wooded slope at low resolution, a terrace edge, a large building, low
multi-path points, and buildings on a steep slope.

Every function returns ``(xyz (n, 3) float64, is_ground (n,) bool)``.
"""

from __future__ import annotations

import math

import numpy as np


def _points(rng: np.random.Generator, width: float, depth: float, spacing: float) -> np.ndarray:
    n = int(width * depth / spacing**2)
    return np.column_stack([rng.random(n) * width, rng.random(n) * depth])


def _noise(rng: np.random.Generator, n: int, sigma: float = 0.05) -> np.ndarray:
    return sigma * rng.standard_normal(n)


def ramp(seed: int = 0, spacing: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A road ramp at 12 % from the plain up to a 5 m high platform 60 m wide (all ground), with
    a vertical retaining wall beside the ramp, and one 20 x 20 m, 7 m high building on the plain."""
    rng = np.random.default_rng(seed)
    xy = _points(rng, 160.0, 100.0, spacing)
    x, y = xy[:, 0], xy[:, 1]
    z = np.clip((x - 50.0) * 0.12, 0.0, 5.0)  # ramp from x = 50 to 91.7
    z = np.where(y < 30.0, z, np.where(x > 91.7, 5.0, 0.0))  # ramp 30 m wide, walls beside it
    building = (np.abs(x - 25.0) < 10.0) & (np.abs(y - 70.0) < 10.0)
    z = z + 7.0 * building + _noise(rng, len(z))
    return np.column_stack([x, y, z]), ~building


def bridge(seed: int = 0, spacing: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A 10 m wide road deck on embankments, spanning a 30 m wide cutting 6 m deep with banks at
    1:1; no returns under the deck. The deck over the cutting is an object, over land ground."""
    rng = np.random.default_rng(seed)
    xy = _points(rng, 140.0, 80.0, spacing)
    x, y = xy[:, 0], xy[:, 1]
    bank = np.clip(np.abs(x - 70.0) - 15.0, 0.0, 6.0)  # 1:1 banks down to the floor
    z = bank - 6.0  # plain at 0, cutting floor at -6 between x = 55 and 85 (banks to 49 and 91)
    deck = np.abs(y - 40.0) < 5.0
    span = deck & (bank < 5.9)  # the deck where the ground falls away below it
    z = np.where(deck, 0.0, z) + _noise(rng, len(z))  # the deck hides the ground below it
    return np.column_stack([x, y, z]), ~span


def wooded_slope(seed: int = 0, spacing: float = 2.4, degrees: float = 35.0
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A hillside of ``degrees`` with a ridge and a valley, half covered by trees (crowns 4 m in
    radius, 8-20 m tall); 60 % of the returns in a crown come from the canopy, the rest from the
    ground below (single returns at low resolution, as the ISPRS samples of sites 5 and 6)."""
    rng = np.random.default_rng(seed)
    xy = _points(rng, 200.0, 200.0, spacing)
    x, y = xy[:, 0], xy[:, 1]
    g = math.tan(math.radians(degrees))
    z = g * (60.0 - np.abs(x - 100.0)) + 3.0 * np.sin(y / 25.0)  # a ridge along y at x = 100
    centres = rng.random((120, 2)) * 200.0
    centres = centres[centres[:, 1] > 100.0]  # the upper half is wooded
    height = rng.uniform(8.0, 20.0, len(centres))
    from scipy.spatial import cKDTree

    d, k = cKDTree(centres).query(xy)
    crown = (d < 4.0) & (rng.random(len(x)) < 0.6)
    z = z + np.where(crown, height[k] - 0.5 * d, 0.0) + _noise(rng, len(z), 0.1)
    return np.column_stack([x, y, z]), ~crown


def terrace(seed: int = 0, spacing: float = 1.0, step: float = 3.0
            ) -> tuple[np.ndarray, np.ndarray]:
    """Two levels of gentle terrain, the upper ``step`` metres higher behind a vertical retaining
    wall running diagonally (both ground), and a 12 x 12 m, 6 m high building on each level."""
    rng = np.random.default_rng(seed)
    xy = _points(rng, 150.0, 120.0, spacing)
    x, y = xy[:, 0], xy[:, 1]
    upper = x + 0.3 * y > 80.0
    z = 0.02 * x + step * upper
    b1 = (np.abs(x - 25.0) < 6.0) & (np.abs(y - 60.0) < 6.0)
    b2 = (np.abs(x - 120.0) < 6.0) & (np.abs(y - 60.0) < 6.0)
    z = z + 6.0 * (b1 | b2) + _noise(rng, len(z))
    return np.column_stack([x, y, z]), ~(b1 | b2)


def large_building(seed: int = 0, spacing: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """An 80 x 50 m flat-roofed hall 9 m high on gently tilted ground, wider than the default
    largest object (the roof must stay an object: it is bounded by walls all round)."""
    rng = np.random.default_rng(seed)
    xy = _points(rng, 160.0, 110.0, spacing)
    x, y = xy[:, 0], xy[:, 1]
    hall = (np.abs(x - 80.0) < 40.0) & (np.abs(y - 55.0) < 25.0)
    z = 0.03 * x + 0.01 * y + 9.0 * hall + _noise(rng, len(x))
    return np.column_stack([x, y, z]), ~hall


def low_points(seed: int = 0, spacing: float = 1.2) -> tuple[np.ndarray, np.ndarray]:
    """Gently rolling ground with single low points and two dense clusters of multi-path returns
    (40 % of the points in a 12 m patch and in a 6 m patch, 15-30 m below the ground), plus a
    building: the low points are not ground and must not pull the terrain down."""
    rng = np.random.default_rng(seed)
    xy = _points(rng, 150.0, 100.0, spacing)
    x, y = xy[:, 0], xy[:, 1]
    z = 2.0 * np.sin(x / 30.0) + 0.01 * y
    building = (np.abs(x - 110.0) < 8.0) & (np.abs(y - 50.0) < 8.0)
    z = z + 8.0 * building
    low = np.zeros(len(x), bool)
    for cx, cy, half in ((40.0, 30.0, 6.0), (75.0, 75.0, 3.0)):
        patch = (np.abs(x - cx) < half) & (np.abs(y - cy) < half)
        low |= patch & (rng.random(len(x)) < 0.4)
    single = rng.choice(np.flatnonzero(~low & ~building), 15, replace=False)
    low[single] = True
    z = z - np.where(low, rng.uniform(15.0, 30.0, len(x)), 0.0) + _noise(rng, len(x))
    return np.column_stack([x, y, z]), ~(low | building)


def steep_town(seed: int = 0, spacing: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A 30 degree hillside with a row of buildings cut into it (8 m high on the downhill side),
    as in the steep urban samples of site 1."""
    rng = np.random.default_rng(seed)
    xy = _points(rng, 120.0, 120.0, spacing)
    x, y = xy[:, 0], xy[:, 1]
    z = math.tan(math.radians(30.0)) * x
    houses = np.zeros(len(x), bool)
    for cy in (15.0, 45.0, 75.0, 105.0):
        h = (np.abs(x - 60.0) < 6.0) & (np.abs(y - cy) < 8.0)
        houses |= h
    roof = math.tan(math.radians(30.0)) * 66.0 + 2.0  # flat roofs 2 m above the uphill ground
    z = np.where(houses, roof, z) + _noise(rng, len(x))
    return np.column_stack([x, y, z]), ~houses


SCENES = {
    "ramp": ramp,
    "bridge": bridge,
    "wooded_slope": wooded_slope,
    "terrace": terrace,
    "large_building": large_building,
    "low_points": low_points,
    "steep_town": steep_town,
}

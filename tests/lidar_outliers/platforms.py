"""Simple physical models of three platforms, for the sensor-profile tests.

Each returns the arrays a LAS file would hold, in acquisition order: ``xyz`` (n, 3) metres,
``gps_time`` (n,) seconds, ``return_number`` and ``number_of_returns`` (n,), ``scan_angle``
(n,) degrees and ``point_source_id`` (n,). Beams are cast analytically; a share of the pulses
meets vegetation first and gives two returns on the same beam.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.lasfiles import write_las

Arrays = dict[str, np.ndarray]


def _two_returns(
    origin: np.ndarray, direction: np.ndarray, end: np.ndarray, t: np.ndarray,
    angle: np.ndarray, share: float, rng: np.random.Generator,
) -> Arrays:
    """Last returns at ``end``; a ``share`` of the pulses also meet vegetation part-way."""
    n = len(end)
    veg = rng.random(n) < share
    length = np.linalg.norm(end - origin, axis=1)
    first = origin + direction * (length * rng.uniform(0.6, 0.95, n))[:, None]
    xyz = np.concatenate([first[veg], end])
    t_all = np.concatenate([t[veg], t])
    order = np.lexsort((np.r_[np.ones(veg.sum()), 2 * np.ones(n)], t_all))
    nr = np.concatenate([np.full(veg.sum(), 2), np.where(veg, 2, 1)])
    rn = np.concatenate([np.ones(veg.sum(), int), np.where(veg, 2, 1)])
    return {
        "xyz": xyz[order], "gps_time": t_all[order], "return_number": rn[order],
        "number_of_returns": nr[order],
        "scan_angle": np.concatenate([angle[veg], angle])[order],
        "point_source_id": np.ones(len(order), dtype=np.uint16),
    }


def aircraft(
    width: float = 200.0, density: float = 90.0, speed: float = 60.0,
    height: float = 1000.0, seed: int = 0,
) -> Arrays:
    """A survey aircraft crossing a ``width`` x ``width`` m tile along x at ``speed`` m/s,
    ``height`` m up, its mirror sweeping the tile's width across track at 100 Hz (the part of
    a wider sweep that falls on the tile); about ``density`` points per m2 on the tile."""
    rng = np.random.default_rng(seed)
    duration = width / speed
    half_angle = np.degrees(np.arctan(width / 2 / height))
    pulses = int(density / 1.3 * width * width)  # 30 % of the pulses give two returns
    t = np.sort(rng.uniform(0, duration, pulses)) + 3.0e8
    phase = (t - t[0]) * 100.0
    angle = half_angle * (4 * np.abs(phase - np.floor(phase + 0.5)) - 1)  # triangle wave
    sensor = np.c_[speed * (t - t[0]), np.zeros(pulses), np.full(pulses, height)]
    direction = np.c_[np.zeros(pulses), np.sin(np.radians(angle)), -np.cos(np.radians(angle))]
    ground = sensor + direction * (height / np.cos(np.radians(angle)))[:, None]
    ground[:, 2] = 0.2 * np.sin(ground[:, 0] / 15) + rng.normal(0, 0.03, pulses)
    out = _two_returns(sensor, direction, ground, t, angle, 0.3, rng)
    out["xyz"] = out["xyz"] + [0.0, width / 2, 0.0]
    return out


def van(
    length: float = 200.0, street: float = 20.0, speed: float = 10.0, rate: float = 8000.0,
    seed: int = 0,
) -> Arrays:
    """A van driving ``length`` m along a street (x) at ``speed`` m/s, a profile scanner 2.5 m
    up sweeping the vertical plane across the street at 100 Hz, ``rate`` pulses a second: the
    road, facades ``street`` m apart and 15 m high, vegetation in front of them; beams into the
    sky give no return."""
    rng = np.random.default_rng(seed)
    pulses = int(rate * length / speed)
    t = np.sort(rng.uniform(0, length / speed, pulses)) + 5.0e5
    angle = np.degrees(2 * np.pi * ((t - t[0]) * 100.0 % 1.0)) - 180.0  # in the scan plane
    up = np.radians(angle)
    direction = np.c_[np.zeros(pulses), np.cos(up), np.sin(up)]
    sensor = np.c_[speed * (t - t[0]), np.zeros(pulses), np.full(pulses, 2.5)]
    half = street / 2
    to_wall = half / np.maximum(np.abs(direction[:, 1]), 1e-9)
    to_ground = np.where(direction[:, 2] < 0, 2.5 / np.maximum(-direction[:, 2], 1e-9), np.inf)
    reach = np.minimum(to_wall, to_ground)
    end = sensor + direction * reach[:, None]
    hit = end[:, 2] <= 15.0
    out = _two_returns(sensor[hit], direction[hit], end[hit], t[hit], angle[hit], 0.2, rng)
    out["xyz"] = out["xyz"] + rng.normal(0, 0.01, out["xyz"].shape)
    return out


def write(path: Path, arrays: Arrays) -> Path:
    """A LAS 1.4 point format 6 file of the arrays (1 mm scale)."""
    xyz = arrays["xyz"]
    scan_angle = np.round(np.clip(arrays["scan_angle"], -180, 180) / 0.006).astype(np.int16)
    return write_las(
        path, xyz, point_format=6, offsets=np.floor(xyz.min(axis=0)),
        gps_time=arrays["gps_time"], point_source_id=arrays["point_source_id"], vlrs=(),
        dims={"return_number": arrays["return_number"],
              "number_of_returns": arrays["number_of_returns"], "scan_angle": scan_angle},
    )

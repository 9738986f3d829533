"""A family of simulated mobile-mapping surveys, like the paper's clouds A, B and C.

The paper's data (an Optech LYNX survey of a parking-lot strip, Leslar, Wang & Hu 2010,
section 4, Table 1) is not public, and a detector tuned to one simulated geometry learns that
geometry. So every seed draws its own survey, within what real systems and streets do
(:mod:`.family` lists every range and the systems they come from): 1-3 profile scanners and
their mounting, rates and noise; the street (road, curbs, sidewalks, facades with windows,
parked cars, poles, trees, an overpass); the drive (passes, lanes, curves, speeds, stops); and
the shape and mix of every outlier kind (:mod:`.outliers`). The condition keeps the paper's
outlier share and character: A about 1.0 % (clumps: exhaust at a standstill, water), B about
0.3 % (spread, the barrier arm in operation), C about 0.01 % (near the asphalt).

Pulses are ray-cast analytically (:mod:`.raycast`, :mod:`.survey`); returns carry range noise,
intensity, return numbers and the mirror angle, and are delivered in a projected world frame
with the vehicle's trajectory. Everything is arrays in, arrays out; :mod:`.files` writes them.
"""

from lidar_outliers.tools.simulator.family import (
    AIRBORNE,
    ARM,
    CONDITIONS,
    EXHAUST,
    GLASS_MP,
    ISOLATED,
    KIND_NAMES,
    MIST,
    MOVING,
    NEAR_SURFACE,
    SCANNERS,
    SURFACE,
    TABLE1,
    WATER,
    Scanner,
)
from lidar_outliers.tools.simulator.files import SCAN_ANGLE_UNIT, stem, to_las, write_simulation
from lidar_outliers.tools.simulator.generate import SimulatedCloud, simulate

__all__ = [
    "AIRBORNE", "ARM", "CONDITIONS", "EXHAUST", "GLASS_MP", "ISOLATED", "KIND_NAMES", "MIST",
    "MOVING", "NEAR_SURFACE", "SCANNERS", "SCAN_ANGLE_UNIT", "SURFACE", "TABLE1", "WATER",
    "Scanner", "SimulatedCloud", "simulate", "stem", "to_las", "write_simulation",
]

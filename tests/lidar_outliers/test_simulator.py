"""The simulator's family: what each seed draws, the paper's shares per condition, and the
physics of every outlier kind, checked against the truth the simulator keeps."""

from __future__ import annotations

import numpy as np
import pytest

from lidar_outliers.tools.simulator import CONDITIONS, KIND_NAMES, TABLE1, simulate
from lidar_outliers.tools.simulator import family as fam
from lidar_outliers.tools.simulator.bodies import Arm, Mover

# One cloud per condition, small enough to be quick and large enough to hold every kind.
SIZES = {"A": (1, 0.1), "B": (1, 0.3), "C": (1, 1.0)}


@pytest.fixture(scope="module")
def clouds():
    return {c: simulate(c, seed, scale) for c, (seed, scale) in SIZES.items()}


def _noise(cloud) -> float:
    """Three range-noise sigmas: how far a return may stray from where its beam met."""
    return 3 * cloud.system.range_sigma


# ------------------------------------------------------------------ the family


def test_same_seed_same_cloud():
    a, b = simulate("C", 5, 0.03), simulate("C", 5, 0.03)
    for name in ("xyz", "gps_time", "intensity", "kind", "scan_angle", "point_source_id",
                 "return_number", "trajectory"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.facts == b.facts


def test_seeds_draw_different_systems_streets_and_drives():
    clouds = [simulate("C", seed, 0.03) for seed in range(6)]
    systems = [c.system for c in clouds]
    assert len({len(s.scanners) for s in systems}) >= 2
    assert len({s.layout for s in systems}) >= 2
    assert len({s.scanners[0].scan_hz for s in systems}) == 6
    assert len({s.range_sigma for s in systems}) == 6
    # rates and speeds as drawn; the size conditioning may pull some to the same bound
    drawn = [fam.draw_system(fam.stream(seed, 1)) for seed in range(6)]
    assert len({s.scanners[0].pulse_hz for s in drawn}) == 6
    assert len({round(s.scanners[0].pulse_hz) for s in systems}) >= 3
    assert len({round(c.facts["drive"]["cruise_speeds"][0], 3) for c in clouds}) >= 3
    assert len({c.street.half_width for c in clouds}) == 6
    assert len({c.frame.azimuth for c in clouds}) == 6
    # the point source ids are the drawn scanners
    for c in clouds:
        assert set(np.unique(c.point_source_id)) <= {s.source_id for s in c.system.scanners}


@pytest.mark.parametrize("seed", range(40))
def test_draws_stay_within_real_systems(seed):
    system = fam.draw_system(fam.stream(seed, 1))
    assert 1 <= len(system.scanners) <= 3 and system.layout in fam.LAYOUTS
    for sc in system.scanners:
        height = system.reference_height + sc.offset[2]
        assert 1.8 <= height <= 3.2 and height >= system.roof_height + 0.25
        assert 50 <= sc.scan_hz <= 250 and 1e5 <= sc.pulse_hz <= 1e6
        assert abs(sc.pitch_deg) <= 45 and abs(sc.offset[1]) <= 0.8
    if system.layout.startswith("butterfly"):
        yaws = sorted(abs(s.yaw_deg) for s in system.scanners[:2])
        assert 25 <= yaws[0] and yaws[1] <= 65
    assert 0.002 <= system.range_sigma <= 0.010
    assert 1.5 <= system.min_range <= 3.0 and 100 <= system.max_range <= 250
    street = fam.draw_street(fam.stream(seed, 2))
    assert 3.5 <= street.half_width <= 9.0 and abs(street.grade) <= 0.04
    assert 0.001 <= street.roughness <= 0.005 and 0 <= street.crown <= 0.12
    assert street.crop_y[0] < 0 < street.crop_y[1]
    for cond in CONDITIONS.values():
        drive = fam.draw_drive(fam.stream(seed, 4, ord(cond.name)), cond, street)
        assert cond.passes[0] <= len(drive.passes) <= cond.passes[1]
        assert all(0.5 <= p.speed <= 20 for p in drive.passes)
        assert cond.stops[0] <= len(drive.stops) <= cond.stops[1]
        assert all(1 <= s.seconds <= 10 for s in drive.stops)


def test_size_conditioning_keeps_rates_and_drive_in_range(clouds):
    for c in clouds.values():
        assert all(1e5 <= s.pulse_hz <= 1e6 for s in c.system.scanners)
        assert all(0.5 <= v <= 20 for v in c.facts["drive"]["cruise_speeds"])
        assert all(b - a <= 10 * c.scale + 1e-6 for a, b in c.motion.stops)
        assert fam.STRIP_RANGE[0] * 0.8 * c.scale <= c.strip <= fam.STRIP_RANGE[1] * 1.25 * c.scale
        assert np.all((c.motion.speed >= -1e-9) & (c.motion.speed <= 20.0 + 1e-6))


# ------------------------------------------------------------------ Table 1


@pytest.mark.parametrize("condition", ["A", "B", "C"])
def test_shares_and_sizes_follow_table1(condition, clouds):
    cloud = clouds[condition]
    points, outliers = TABLE1[condition]
    share = cloud.is_outlier.mean()
    if condition == "C":  # 31 outliers at full size: one more or less is 3 %
        assert abs(cloud.is_outlier.sum() - outliers * cloud.scale) <= 3
    else:
        assert share == pytest.approx(outliers / points, rel=0.02)
    assert 0.6 <= len(cloud) / (points * cloud.scale) <= 1.4
    np.testing.assert_array_equal(cloud.is_outlier, cloud.kind != 0)


@pytest.mark.parametrize("condition", ["A", "B", "C"])
def test_every_kind_the_condition_names_is_there(condition, clouds):
    cloud = clouds[condition]
    cond = CONDITIONS[condition]
    present = set(np.unique(cloud.kind[cloud.is_outlier]).tolist())
    assert present <= set(cond.kinds)
    assert set(cond.kinds) - cond.optional <= present
    # the drawn mix names every kind of the condition, with the weights summing to one
    mix = cloud.facts["outliers"]["mix"]
    assert set(mix) == {KIND_NAMES[k] for k in cond.kinds}
    assert sum(mix.values()) == pytest.approx(1.0, abs=1e-3)


def test_condition_character(clouds):
    a, b, c = clouds["A"], clouds["B"], clouds["C"]
    count = {k: np.bincount(x.kind, minlength=len(KIND_NAMES)) for k, x in clouds.items()}
    # A: clumps dominate (exhaust plume and the water: mirror images and mist)
    clumped = count["A"][[fam.EXHAUST, fam.WATER, fam.MIST]].sum()
    assert clumped > 0.6 * a.is_outlier.sum()
    # A and B stood still at least once in A; the arm operates in A and B only
    assert len(a.motion.stops) >= 1
    assert count["A"][fam.ARM] > 0 and count["B"][fam.ARM] > 0 and count["C"][fam.ARM] == 0
    # C: most outliers within a few cm of the ground
    assert count["C"][fam.NEAR_SURFACE] > 0.5 * c.is_outlier.sum()
    assert b.is_outlier.mean() < a.is_outlier.mean()


# ------------------------------------------------------------------ physics of the kinds


def test_mirror_images_lie_below_the_water_and_behind_the_glass(clouds):
    for cloud in (clouds["A"], clouds["B"]):
        water = cloud.kind == fam.WATER
        assert water.any()
        below = cloud.xyz[water, 2] - cloud.scene_height(cloud.xyz[water])
        assert np.all(below < 0.05 - _noise(cloud))  # at least 5 cm below the mirror
        glass = cloud.kind == fam.GLASS_MP
        if not glass.any():
            continue
        p = cloud.local(cloud.xyz[glass])
        facade_y = {f.side: f.y for f in cloud.street.facades}
        side = np.sign(p[:, 1]).astype(int)
        behind = np.array([abs(y) >= facade_y.get(s, np.inf) - _noise(cloud)
                           for y, s in zip(p[:, 1], side, strict=True)])
        assert behind.all()


def test_returns_lie_along_their_beam_in_the_scan_plane(clouds):
    """Every return, mirror images included, lies in its scanner's plane at that instant
    (the scanner times the path along the outgoing beam) and within its range limits."""
    for cloud in clouds.values():
        origin = cloud.scanner_positions(cloud.gps_time, cloud.point_source_id)
        ray = cloud.xyz - origin
        rng = np.linalg.norm(ray, axis=1)
        assert np.all(rng <= cloud.system.max_range + _noise(cloud))
        assert np.all(rng >= cloud.system.min_range - _noise(cloud))
        local_origin = cloud.local(origin)
        local_ray = cloud.local(cloud.xyz) - local_origin
        for sc in cloud.system.scanners:
            m = cloud.point_source_id == sc.source_id
            _, f, left, up = cloud.motion.at(cloud.gps_time[m])
            n_v, _, _ = sc.plane_basis()
            normal = n_v[0] * f + n_v[1] * left + n_v[2] * up
            off_plane = np.abs(np.sum(local_ray[m] * normal, axis=1))
            assert np.all(off_plane < 1e-4)


def test_mist_fills_its_band_above_the_road(clouds):
    for cloud in (clouds["A"], clouds["B"]):
        mist = cloud.kind == fam.MIST
        assert mist.any()
        p = cloud.local(cloud.xyz[mist])
        height = p[:, 2] - cloud.street.road_z(p[:, 0], p[:, 1])
        lo = min(patch.band[0] for patch in cloud.plan.patches)
        hi = max(patch.band[1] for patch in cloud.plan.patches)
        assert 0.02 <= lo and hi <= 1.0
        assert np.all((height >= lo - _noise(cloud)) & (height <= hi + _noise(cloud)))


def test_near_surface_and_droplets_stay_above_the_ground(clouds):
    c = clouds["C"]
    near = c.kind == fam.NEAR_SURFACE
    dz = c.xyz[near, 2] - c.scene_height(c.xyz[near])
    assert np.all((dz > 0.015 - _noise(c)) & (dz < 0.06 + _noise(c) + 0.005))
    a = clouds["A"]
    plume = a.kind == fam.EXHAUST
    p = a.local(a.xyz[plume])
    assert np.all(p[:, 2] - a.street.road_z(p[:, 0], p[:, 1]) > -_noise(a))
    # droplet returns come first: the surface behind answers as the last return, or not at all
    droplets = np.isin(a.kind, (fam.EXHAUST, fam.MIST))
    assert np.all(a.return_number[droplets] == 1)


def test_standstill_plume_lies_in_the_scan_planes(clouds):
    """Where the vehicle stood, the scanners sliced the plume in their fixed planes."""
    cloud = clouds["A"]
    stood = np.zeros(len(cloud), dtype=bool)
    for a, b in cloud.motion.stops:
        stood |= (cloud.gps_time >= a) & (cloud.gps_time <= b)
    plume = (cloud.kind == fam.EXHAUST) & stood
    assert plume.sum() > 20
    p = cloud.local(cloud.xyz[plume])
    src = cloud.point_source_id[plume]
    t = cloud.gps_time[plume]
    for sc in cloud.system.scanners:
        m = src == sc.source_id
        if not m.any():
            continue
        o = cloud.motion.place(t[m], np.array(sc.offset))
        _, f, left, up = cloud.motion.at(t[m])
        n_v, _, _ = sc.plane_basis()
        normal = n_v[0] * f + n_v[1] * left + n_v[2] * up
        assert np.all(np.abs(np.sum((p[m] - o) * normal, axis=1)) < 1e-4)
        # one plane: the normal did not turn while the vehicle stood
        assert np.ptp(normal, axis=0).max() < 1e-6


def test_moving_bodies_are_seen_where_they_were_at_that_moment(clouds):
    """A return of a moving body lies on the body at its own time, and not where the body
    was two seconds earlier or later (another scan of that place sees the street)."""
    for cloud in (clouds["A"], clouds["B"]):
        moving = np.isin(cloud.kind, (fam.MOVING, fam.ARM, fam.AIRBORNE))
        p = cloud.local(cloud.xyz[moving])
        t = cloud.gps_time[moving]
        pad = _noise(cloud) + 0.01
        bodies = cloud.plan.bodies
        on_any = np.zeros(len(p), dtype=bool)
        for body in bodies:
            on = body.contains(p, t, pad)
            on_any |= on
            if isinstance(body, Mover) and on.any():
                gone = ~body.contains(p[on], t[on] - 2.0, pad) & ~body.contains(
                    p[on], t[on] + 2.0, pad)
                assert gone.mean() > 0.99
        kind = cloud.kind[moving]
        rain = kind == fam.AIRBORNE  # rain drops are no body: only birds are
        assert np.all(on_any[~rain])
        assert any(isinstance(b, Arm) for b in bodies)
        # each body is present for one stretch of time
        for code in (fam.MOVING, fam.ARM):
            times = cloud.gps_time[cloud.kind == code]
            assert len(times) and np.ptp(times) < 30.0


def test_trajectory_is_the_reference_point_the_scanners_ride_on(clouds):
    for cloud in clouds.values():
        traj = cloud.trajectory
        assert np.all(np.diff(traj[:, 0]) > 0)
        assert traj[0, 0] <= cloud.gps_time.min() and cloud.gps_time.max() <= traj[-1, 0]
        pose = cloud.pose()
        np.testing.assert_allclose(traj, pose[::2, :4])
        # the reference point stands on the road, the reference height up the body's axis
        p = cloud.local(traj[:, 1:])
        ground = cloud.street.road_z(p[:, 0], p[:, 1])
        assert np.allclose(p[:, 2] - ground, cloud.system.reference_height, atol=0.01)
        # each scanner's returns lie within its range of where the trajectory and lever
        # arm put it (the attitude moves it by a few cm at most)
        arms = {a[0]: np.array(a[1:]) for a in cloud.lever_arms()}
        for sid, arm in arms.items():
            m = cloud.point_source_id == sid
            if not m.any():
                continue
            ref = np.column_stack([np.interp(cloud.gps_time[m], traj[:, 0], traj[:, k])
                                   for k in (1, 2, 3)])
            true = cloud.scanner_positions(cloud.gps_time[m], cloud.point_source_id[m])
            # (the trajectory file has every other pose: interpolating it costs < 1 mm)
            assert np.linalg.norm(true - ref, axis=1).max() <= np.linalg.norm(arm) + 1e-3
            assert np.linalg.norm(cloud.xyz[m] - ref, axis=1).max() <= (
                cloud.system.max_range + np.linalg.norm(arm))


def test_pulses_keep_their_scanner_clock(clouds):
    """Returns of one scanner come in time order on its pulse grid; beams into the sky or
    out of the cut leave gaps."""
    cloud = clouds["B"]
    for sc in cloud.system.scanners:
        t = cloud.gps_time[cloud.point_source_id == sc.source_id]
        if len(t) < 100:
            continue
        steps = np.diff(t)
        assert np.all(steps >= 0)
        k = t * sc.pulse_hz
        assert np.abs(k - np.round(k)).max() < 1e-3
        assert np.median(steps[steps > 0]) == pytest.approx(1 / sc.pulse_hz, rel=1e-3)


def test_coordinates_look_like_a_projected_delivery(clouds):
    cloud = clouds["C"]
    assert 3e5 <= cloud.xyz[:, 0].min() and cloud.xyz[:, 0].max() <= 7.2e5
    assert 4e6 <= cloud.xyz[:, 1].min() and cloud.xyz[:, 1].max() <= 6.1e6
    back = cloud.frame.to_world(cloud.local(cloud.xyz))
    np.testing.assert_allclose(back, cloud.xyz, atol=1e-6)
    assert 0 <= cloud.gps_time.min() and cloud.gps_time.max() < 604800

"""Sensor profiles chosen from the evidence files carry: real files, and physical models of an
aircraft and a van written as LAS and read back."""

from __future__ import annotations

import typing
from pathlib import Path

import numpy as np
import pytest

from lidar_outliers.cli.detect import profile_choices
from lidar_outliers.lasio import inspect_las, read_profile_sample
from lidar_outliers.params import PipelineParams, default_stages
from lidar_outliers.process import process_file
from lidar_outliers.profiles import (
    PROFILES,
    choose_profile,
    default_pipeline,
    header_hint,
    profile_evidence,
    profile_stages,
)
from tests.lasfiles import write_las
from tests.lidar_outliers.platforms import aircraft, van, write

DATA = Path(__file__).resolve().parents[1] / "data"
#: The shared real data (``shared/data`` beside the checkout or a parent of it), when present.
SHARED = next((p / "shared" / "data" for p in Path(__file__).resolve().parents
               if (p / "shared" / "data").is_dir()), Path("/nonexistent"))


def write_sweep(path: Path, xyz: np.ndarray, ring: bool, point_format: int = 6) -> Path:
    """Points with a ``ring`` channel dimension (a spinning sensor's sweep) or without."""
    extra = {"ring": (np.arange(len(xyz)) % 64).astype(np.uint8)} if ring else None
    return write_las(path, xyz, point_format=point_format, offsets=np.floor(xyz.min(axis=0)),
                     extra=extra, vlrs=())


def file_choice(path: Path, **sample: int):
    facts = inspect_las(path).to_dict()
    return choose_profile(profile_evidence(facts, read_profile_sample(path, **sample)))


def test_profile_names_agree_everywhere():
    literal = typing.get_args(PipelineParams.model_fields["profile"].annotation)
    assert list(literal) == profile_choices() == ["auto", *sorted(PROFILES, key=literal.index)]


def test_spinning_sweep_in_sensor_frame(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-50, 50, (2000, 3))
    path = write_sweep(tmp_path / "sweep.las", xyz, ring=True)
    choice = file_choice(path)
    assert choice.profile == "spinning" and choice.confidence == "high"
    profile, stages = default_pipeline(choice.evidence)
    assert profile == "spinning" and stages[0].detector == "snow"


def test_ring_without_the_sensor_origin_is_not_spinning(tmp_path):
    """A registered (map-frame) sweep: the origin test fails, snow's ranges would be wrong."""
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 10, (20000, 3)) + np.array([5e5, 5e6, 100.0])
    choice = file_choice(write_sweep(tmp_path / "map.las", xyz, ring=True))
    assert choice.profile != "spinning" and "sensor origin is outside" in choice.reason


def test_van_over_a_long_street_is_mobile(tmp_path):
    """A profile scanner on a van: 40 points per m2 of its bounding box (under the old density
    rule's 50, so it was taken for airborne); its beams look sideways and it drives at 10 m/s."""
    path = write(tmp_path / "van.las", van())
    facts = inspect_las(path).to_dict()
    lo, hi = facts["bounds"]["min"], facts["bounds"]["max"]
    assert 30 < facts["points"] / ((hi[0] - lo[0]) * (hi[1] - lo[1])) < 50
    choice = file_choice(path)
    assert choice.profile == "mobile" and choice.confidence == "high"
    assert choice.evidence["beams_down_share"] < 0.2
    assert choice.evidence["speed_m_s"] == pytest.approx(10, rel=0.05)
    assert [s.detector for s in default_pipeline(choice.evidence)[1]] == \
        [s.detector for s in default_stages(True)]
    # A short slice of it, read as a small sample of runs: still mobile.
    assert file_choice(path, max_points=20_000, run_points=500).profile == "mobile"


def test_van_without_multiple_returns_is_mobile_by_its_speed(tmp_path):
    arrays = van(seed=1)
    single = arrays["number_of_returns"] == 1
    arrays = {k: v[single] for k, v in arrays.items()}
    choice = file_choice(write(tmp_path / "van1.las", arrays))
    assert choice.profile == "mobile" and choice.evidence["pulses"] == 0
    assert "platform speed" in choice.reason


def test_dense_airborne_tile_is_airborne(tmp_path):
    """90 points per m2 (an IGN LiDAR HD tile's density, over the old rule's 50): beams look
    down, whether the whole file is read or only runs after seeks."""
    path = write(tmp_path / "air.las", aircraft(width=60.0))
    facts = inspect_las(path).to_dict()
    assert facts["points"] / (60 * 60) == pytest.approx(90, rel=0.05)
    for sample in ({}, {"max_points": 20_000, "run_points": 500}):
        choice = file_choice(path, **sample)
        assert choice.profile == "airborne" and choice.confidence == "high"
        assert choice.evidence["beams_down_share"] == 1.0
        assert choice.evidence["speed_m_s"] == pytest.approx(60, rel=0.05)


def test_single_return_aircraft_is_airborne_by_its_speed(tmp_path):
    arrays = aircraft(width=150.0, density=6.0, seed=2)
    last = arrays["return_number"] == arrays["number_of_returns"]
    arrays = {k: v[last] for k, v in arrays.items()}
    choice = file_choice(write(tmp_path / "air1.las", arrays))
    assert choice.profile == "airborne" and "platform speed" in choice.reason


def test_without_evidence_the_airborne_pipeline_runs_and_says_so():
    choice = choose_profile(profile_evidence({"points": 25408, "extra_dimensions": [],
                                              "bounds": {"min": [0, 0, 0], "max": [18, 12, 16]}}))
    assert choice.profile == "airborne" and choice.confidence == "low"
    assert "flags least" in choice.reason
    assert choice.evidence["points_per_m2"] == pytest.approx(25408 / 216, rel=1e-3)


def test_decision_rules_in_order():
    beams_down = {"pulses": 500, "beams_down_share": 0.97}
    beams_side = {"pulses": 500, "beams_down_share": 0.3}
    assert choose_profile({**beams_down, "speed_m_s": 8.0, "speed_windows": 20}).profile \
        == "airborne"  # a drone: slow, but it looks down
    assert choose_profile({**beams_side, "speed_m_s": 60.0, "speed_windows": 20}).profile \
        == "mobile"
    assert choose_profile({**beams_side, "speed_m_s": 0.1, "speed_windows": 20}).profile \
        == "terrestrial"
    assert choose_profile({"pulses": 10, "beams_down_share": 0.0}).profile == "airborne"
    assert choose_profile({"speed_m_s": 30.0, "speed_windows": 20}).confidence == "low"
    assert choose_profile({"speed_m_s": 50.0, "speed_windows": 1}).confidence == "low"
    assert choose_profile({"occupied_points_per_m2": 2000.0, "usable_gps_time": False}
                          ).profile == "terrestrial"
    assert choose_profile({"occupied_points_per_m2": 2000.0, "usable_gps_time": True}
                          ).profile == "mobile"
    assert choose_profile({"scan_angle_max_deg": 90.0}).profile == "mobile"
    assert choose_profile({"generating_software": "RiSCAN_PRO"}).profile == "terrestrial"


def test_header_hints():
    assert header_hint("ALSXX", "ALSXX_PP V2.70") == ("airborne", "ALS")
    assert header_hint("RIEGL VMX-450", "") == ("mobile", "VMX")
    assert header_hint("", "TerraScan") is None  # serves every kind of sensor
    assert header_hint("", "also written by hand") is None


def test_terrestrial_runs_height_field_only():
    assert [s.detector for s in profile_stages("terrestrial", True)] == ["height_field"]


def test_unknown_profile_is_refused():
    with pytest.raises(ValueError, match="unknown profile"):
        profile_stages("satellite", True)


def test_process_file_reports_the_choice(tmp_path):
    path = write(tmp_path / "air.las", aircraft(width=40.0, density=20.0, seed=3))
    stats = process_file(path, tmp_path / "out.las")
    assert stats["profile"] == "airborne" and stats["profile_source"] == "auto"
    assert stats["profile_confidence"] == "high" and "nadir" in stats["profile_reason"]
    assert stats["profile_facts"]["sampled_points"] == stats["input"]["points"]
    assert [s["detector"] for s in stats["stages"]] == ["detached"]
    named = process_file(path, tmp_path / "out2.las", {"profile": "mobile"})
    assert named["profile_source"] == "given" and named["profile_confidence"] is None


# --------------------------------------------------------------------------- real files


@pytest.mark.parametrize("name, confidence", [
    ("laspy__append-bug.laz", "high"),
    ("norway_lasrs_32-1-472-150-76.laz", "high"),
    ("ign_crop_duplicate.laz", "high"),
    # 114 points per m2 (taken for mobile by density), single return, four time stamps: no
    # evidence either way, so the pipeline that does least harm, and it says so.
    ("nebraska_laspy_wkt_geotiff_vlrs_metres.las", "low"),
])
def test_real_airborne_tiles_in_tests_data(name, confidence):
    choice = file_choice(DATA / "airborne" / name)
    assert choice.profile == "airborne" and choice.confidence == confidence
    assert default_pipeline(choice.evidence)[1][0].detector == "detached"


@pytest.mark.parametrize("name, profile", [
    ("pdal__las__4_6_crop.las", "airborne"),       # multiple returns looking down
    ("laspy__simple1_3.las", "airborne"),           # Leica ALS header, no other evidence
    ("pdal__autzen__autzen.las", "airborne"),       # Autzen ALS: too few points to tell
])
def test_real_format_files(name, profile):
    path = DATA / "formats" / name
    if not path.exists():
        pytest.skip(f"no copy of {name}")
    assert file_choice(path).profile == profile


@pytest.mark.parametrize("name", [
    "zurich_LAStools.laz", "ign_las_with_several_extra_byte_bloc.laz",
    "ign_test_semis_2021_0382_6565_decimated.laz",
])
def test_shared_airborne_tiles(name):
    """Zurich (66 points per m2) was taken for mobile by density."""
    path = SHARED / "airborne" / name
    if not path.exists():
        pytest.skip("no shared airborne data")
    assert file_choice(path).profile == "airborne"


def test_shared_snow_frames_isprs_samples_and_a_terrestrial_scan():
    wads = sorted((SHARED / "wads").glob("*.laz"))
    isprs = sorted((SHARED / "isprs").glob("*.laz"))
    tls = SHARED / "formats" / "pdal__copc__lone-star.copc.laz"
    if not wads or not isprs or not tls.exists():
        pytest.skip("no shared data")
    assert {file_choice(p).profile for p in wads} == {"spinning"}
    assert {file_choice(p).profile for p in isprs} == {"airborne"}
    assert file_choice(tls).profile == "terrestrial"  # RiSCAN export, GPS time all 0

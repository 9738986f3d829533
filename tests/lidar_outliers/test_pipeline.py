"""pipeline: stage semantics, classes, reference-class statistics, precision, progress."""

from __future__ import annotations

import json

import laspy
import numpy as np
import pytest

from algorithms import ground
from lidar_outliers import lasio
from lidar_outliers.cloud import Cloud
from lidar_outliers.errors import ParameterError
from lidar_outliers.params import FLAG_BITS, PipelineParams, parse_pipeline_params
from lidar_outliers.pipeline import resolve_stages, run_pipeline, usable_gps_time
from lidar_outliers.process import process_file
from tests.lasfiles import scan_line_cloud, write_las


def _cloud(xyz: np.ndarray, t: np.ndarray | None, cls: np.ndarray | None = None) -> Cloud:
    n = xyz.shape[0]
    zeros = np.zeros(n, np.uint8)
    return Cloud(
        xyz=xyz, origin=np.zeros(3), gps_time=t, point_source_id=np.ones(n, np.uint16),
        classification=zeros.copy() if cls is None else cls,
    )


@pytest.fixture
def spiky(rng):
    xyz, t, spiked = scan_line_cloud(3000, rng, spikes=30, spike_size=0.5)
    return xyz, t, spiked


def test_later_stage_sees_only_points_earlier_stages_left(spiky):
    from algorithms.section import detect_section

    xyz, t, _ = spiky
    params = PipelineParams.model_validate(
        {"pipeline": [{"detector": "temporal", "sigma": 0.003},
                      {"detector": "section", "section_size": 4.0, "sigma": 0.003}]}
    )
    result = run_pipeline(_cloud(xyz, t), params)
    by_temporal = (result.flags & 1) != 0
    assert by_temporal.sum() >= 30
    rest = ~by_temporal
    # The section stage never saw the temporal outliers...
    assert np.all(np.isnan(result.scores["section"][by_temporal]))
    assert result.statistics["stages"][1]["points_in"] == int(rest.sum())
    # ...and on the others it is exactly the detector run on the remaining points alone.
    direct = detect_section(xyz[rest], section_size=4.0, sigma=0.003, alpha=0.001)
    np.testing.assert_array_equal(result.scores["section"][rest],
                                  direct.score.astype(np.float32))
    np.testing.assert_array_equal((result.flags[rest] & 4) != 0, direct.flagged)
    assert not np.any((result.flags & 1) & (result.flags & 4))
    assert result.scores["temporal"].dtype == np.float32


def test_classes_noise_and_ground(spiky):
    xyz, t, _ = spiky
    cls = np.full(len(t), 5, np.uint8)
    params = PipelineParams.model_validate(
        {"pipeline": [{"detector": "temporal", "sigma": 0.003}, {"detector": "ground"}],
         "noise_class": 18}
    )
    result = run_pipeline(_cloud(xyz, t, cls), params)
    flagged = result.flags != 0
    assert np.all(result.classification[flagged] == 18)
    expected = ground.classify_ground(xyz[~flagged], slope_threshold=45.0, max_iterations=50)
    np.testing.assert_array_equal(result.classification[~flagged],
                                  np.where(expected.is_ground, 2, 1))
    stage = result.statistics["stages"][1]
    assert stage["points_ground"] + stage["points_other"] == int((~flagged).sum())
    assert "ground" not in result.scores


def test_classify_off_leaves_classes_and_file_untouched(tmp_path, spiky):
    xyz, t, _ = spiky
    cls = np.random.default_rng(1).integers(0, 6, len(t)).astype(np.uint8)
    src = write_las(tmp_path / "in.las", xyz, gps_time=t, classification=cls)
    params = {"pipeline": [{"detector": "temporal", "sigma": 0.003}], "classify": False}
    stats = process_file(src, tmp_path / "off.las", params)
    off = laspy.read(tmp_path / "off.las")
    np.testing.assert_array_equal(off.classification, cls)
    assert stats["overall"]["points_flagged"] == int((np.asarray(off.outlier_flags) != 0).sum()) > 0
    process_file(src, tmp_path / "on.las", {**params, "classify": True})
    on = laspy.read(tmp_path / "on.las")
    flagged = np.asarray(on.outlier_flags) != 0
    np.testing.assert_array_equal(np.asarray(on.classification)[flagged], 7)
    np.testing.assert_array_equal(np.asarray(on.classification)[~flagged], cls[~flagged])


def test_reference_classes_confusion_counts(tmp_path, spiky):
    xyz, t, spiked = spiky
    cls = np.ones(len(t), np.uint8)
    cls[spiked] = 7
    cls[np.flatnonzero(~spiked)[:5]] = 18  # "noise" the detector cannot see
    src = write_las(tmp_path / "in.las", xyz, gps_time=t, classification=cls)
    stats = process_file(src, tmp_path / "out.las",
                         {"pipeline": [{"detector": "temporal", "sigma": 0.003}],
                          "reference_classes": [7, 18]})
    flagged = np.asarray(laspy.read(tmp_path / "out.las").outlier_flags) != 0
    truth = np.isin(cls, [7, 18])
    conf = stats["stages"][0]["confusion"]
    assert conf["outliers"] == int(truth.sum()) == 35
    assert conf["outliers_identified"] == int((truth & flagged).sum())
    assert conf["non_outliers_identified"] == int((~truth & flagged).sum())
    assert conf["outliers_missed"] == int((truth & ~flagged).sum())
    assert conf["pct_cloud_identified"] == pytest.approx(100 * flagged.sum() / len(t))
    assert stats["overall"]["confusion"] == conf
    json.dumps(stats, allow_nan=False)


def test_ground_scores_with_reference_class_2(spiky):
    xyz, t, _ = spiky
    cls = np.where(xyz[:, 2] < 0, 2, 1).astype(np.uint8)
    params = PipelineParams.model_validate(
        {"pipeline": [{"detector": "ground"}], "reference_classes": [2]}
    )
    result = run_pipeline(_cloud(xyz, t, cls), params)
    scores = result.statistics["stages"][0]["ground_scores"]
    predicted = result.classification == 2
    truth = cls == 2
    assert scores["ground_as_object"] == int((truth & ~predicted).sum())
    assert scores["object_as_ground"] == int((~truth & predicted).sum())
    assert "confusion" not in result.statistics["overall"]  # no noise classes named


#: Profile evidence of a ground vehicle (a van at 10 m/s, its beams looking sideways).
VAN = {"speed_m_s": 10.0, "speed_windows": 20, "pulses": 400, "beams_down_share": 0.2}


def test_default_pipeline_and_reason():
    t = np.linspace(0, 1, 50)
    stages, note = resolve_stages(PipelineParams(), t, evidence=VAN)
    assert [s.detector for s in stages] == ["transient", "height_field"]
    assert note["pipeline_source"] == "default" and note["profile"] == "mobile"
    assert note["profile_source"] == "auto" and note["profile_confidence"] == "high"
    assert "looking sideways" in note["profile_reason"]
    assert note["profile_facts"]["speed_m_s"] == 10.0
    for gps, why in ((None, "no gps_time"), (np.zeros(50), "same"), (np.full(3, np.nan), "NaN")):
        stages, note = resolve_stages(PipelineParams(), gps, evidence=VAN)
        assert [s.detector for s in stages] == ["height_field"]
        assert why in note["default_reason"] and "height_field" in note["default_reason"]
        assert usable_gps_time(gps)[0] is False
    stages, note = resolve_stages(PipelineParams(pipeline=[{"detector": "section"}]), None)
    assert note == {"pipeline_source": "given"}
    # Without evidence: the pipeline that does least harm, and the statistics say so.
    stages, note = resolve_stages(PipelineParams(), t)
    assert [s.detector for s in stages] == ["detached"]
    assert note["profile"] == "airborne" and note["profile_confidence"] == "low"
    # A named profile wins over the evidence; the paper's pipeline runs when named.
    stages, note = resolve_stages(PipelineParams(profile="airborne"), t, evidence=VAN)
    assert [s.detector for s in stages] == ["detached"] and note["profile_source"] == "given"
    stages, _ = resolve_stages(PipelineParams(profile="terrestrial"), t)
    assert [s.detector for s in stages] == ["height_field"]
    stages, _ = resolve_stages(parse_pipeline_params(
        {"pipeline": [{"detector": "temporal"}, {"detector": "patch"}]}), t)
    assert [s.detector for s in stages] == ["temporal", "patch"]


def test_default_pipeline_end_to_end_without_gps_time(tmp_path, rng):
    # The mobile profile on a file without gps_time runs height_field alone.
    xy = rng.uniform(0, 1.5, (300, 2))
    xyz = np.column_stack([xy, rng.normal(0, 0.003, 300)])
    src = write_las(tmp_path / "pf0.las", xyz, point_format=0)
    stats = process_file(src, tmp_path / "out.las", {"profile": "mobile"})
    assert [s["detector"] for s in stats["stages"]] == ["height_field"]
    assert "no gps_time" in stats["default_reason"] and stats["profile"] == "mobile"
    assert set(laspy.read(tmp_path / "out.las").point_format.extra_dimension_names) == {
        "outlier_flags", "height_field_score"}


def _profile_cloud(xyz: np.ndarray, t: np.ndarray | None, rng) -> Cloud:
    cloud = _cloud(xyz, t)
    cloud.intensity = rng.integers(0, 200, len(xyz)).astype(np.uint16)
    return cloud


def test_default_profile_chosen_by_run_pipeline(rng):
    """Each profile's stages run through run_pipeline, chosen from the cloud's own points when
    no file evidence is given; the statistics name the evidence used."""
    # Mobile: a 4 m wide strip recorded by a platform moving 1 m/s along x.
    n = 4000
    t = np.sort(rng.uniform(0, 10, n))
    xyz = np.column_stack([t + rng.normal(0, 0.3, n), rng.uniform(0, 4, n),
                           rng.normal(0, 0.003, n)])
    res = run_pipeline(_profile_cloud(xyz, t, rng), PipelineParams())
    st = res.statistics
    assert [s["detector"] for s in st["stages"]] == ["transient", "height_field"]
    assert st["profile"] == "mobile" and st["profile_facts"]["speed_m_s"] < 2
    assert set(res.scores) == {"transient", "height_field"}
    # Airborne: an aircraft at 60 m/s over 200 m x 200 m (0.1 points per m2).
    ta = np.sort(rng.uniform(0, 3.3, n))
    sparse = np.column_stack([60 * ta, rng.uniform(0, 200, n), rng.normal(0, 0.05, n)])
    st = run_pipeline(_profile_cloud(sparse, ta, rng), PipelineParams()).statistics
    assert [s["detector"] for s in st["stages"]] == ["detached"]
    assert st["profile"] == "airborne" and "platform speed" in st["profile_reason"]
    # Spinning: a sweep around the sensor origin, with the file's ring dimension in the facts.
    az = rng.uniform(0, 2 * np.pi, n)
    rr = rng.uniform(3, 30, n)
    sweep = np.column_stack([rr * np.cos(az), rr * np.sin(az), rng.normal(-1.7, 0.01, n)])
    facts = {"points": n, "extra_dimensions": ["ring"], "has_gps_time": True,
             "bounds": {"min": sweep.min(axis=0).tolist(), "max": sweep.max(axis=0).tolist()}}
    st = run_pipeline(_profile_cloud(sweep, t, rng), PipelineParams(), facts=facts).statistics
    assert [s["detector"] for s in st["stages"]] == ["snow"]
    assert st["profile"] == "spinning" and st["profile_facts"]["channel_dimensions"] == ["ring"]
    by_bit = st["overall"]["flagged_by_bit"]
    assert set(by_bit) == set(FLAG_BITS)  # every registered bit, not the paper's 3
    assert by_bit["snow"] == st["stages"][0]["points_flagged"]



def test_far_coordinates_and_late_gps_time_give_the_same_flags(tmp_path, spiky):
    xyz, t, _ = spiky
    params = {"pipeline": [{"detector": "temporal"}, {"detector": "section", "sigma": 0.003}]}
    far = np.array([4_999_000.0, 5_000_000.0, 100.0])
    near_file = write_las(tmp_path / "near.las", xyz, gps_time=t)
    far_file = write_las(tmp_path / "far.las", xyz + far, gps_time=t + 500_000.0,
                         offsets=tuple(far))
    s_near = process_file(near_file, tmp_path / "near_out.las", params)
    s_far = process_file(far_file, tmp_path / "far_out.las", params)
    a, b = laspy.read(tmp_path / "near_out.las"), laspy.read(tmp_path / "far_out.las")
    assert np.asarray(a.outlier_flags).any()
    np.testing.assert_array_equal(a.outlier_flags, b.outlier_flags)
    np.testing.assert_allclose(a.temporal_score, b.temporal_score, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(a.section_score, b.section_score, rtol=1e-5, atol=1e-5)
    # Time steps of 1e-4 s next to 5e5 s carry ~1e-6 relative rounding: sigma agrees to that.
    sigma_near, sigma_far = (s["stages"][0]["info"]["sigma"] for s in (s_near, s_far))
    assert sigma_near == pytest.approx(sigma_far, rel=1e-4)


def test_progress_is_reported_and_its_exception_propagates(tmp_path, spiky):
    xyz, t, _ = spiky
    src = write_las(tmp_path / "in.las", xyz, gps_time=t)
    two_stages = {"pipeline": [{"detector": "temporal"}, {"detector": "section"}]}
    streaming = {"pipeline": [{"detector": "temporal"}]}
    for params, words in ((two_stages, ("reading", "temporal", "section", "writing")),
                          (streaming, ("temporal (streaming)",))):
        seen: list[tuple[float, str]] = []
        process_file(src, tmp_path / "ok.las", params, streaming=True,
                     progress=lambda f, m, seen=seen: seen.append((f, m)), chunk_points=500)
        fractions = [f for f, _ in seen]
        assert fractions == sorted(fractions) and fractions[0] == 0.0 and fractions[-1] == 1.0
        assert len(seen) >= 6
        messages = " ".join(m for _, m in seen)
        assert all(word in messages for word in words), messages

    class Cancelled(Exception):
        pass

    for params, stop_at in ((two_stages, "section"), (two_stages, "writing"),
                            (streaming, "streaming")):
        def progress(fraction: float, message: str, stop_at=stop_at) -> None:
            if stop_at in message and fraction > 0.4:
                raise Cancelled(stop_at)

        out_dir = tmp_path / stop_at
        with pytest.raises(Cancelled):
            process_file(src, out_dir / "out.las", params, progress=progress, streaming=True,
                         stats_path=out_dir / "s.json", chunk_points=500)
        assert not out_dir.exists() or list(out_dir.iterdir()) == []


def test_empty_file_is_processed(tmp_path):
    src = write_las(tmp_path / "empty.las", np.zeros((0, 3)), gps_time=np.zeros(0))
    stats = process_file(src, tmp_path / "out.las", {"pipeline": [{"detector": "temporal"}]})
    assert stats["stages"][0]["skipped"] and stats["overall"]["points"] == 0
    assert laspy.read(tmp_path / "out.las").header.point_count == 0


def test_parameter_errors_name_the_field(tmp_path, spiky):
    with pytest.raises(ParameterError, match=r"pipeline\[0\]\.n1: .*greater than or equal to 1"):
        parse_pipeline_params({"pipeline": [{"detector": "temporal", "n1": 0}]})
    with pytest.raises(ParameterError, match=r"pipeline\[1\]\.kk: unknown parameter"):
        parse_pipeline_params('{"pipeline": [{"detector": "temporal"}, {"detector": "patch", '
                              '"kk": 3}]}')
    with pytest.raises(ParameterError, match="unknown detector 'median'"):
        parse_pipeline_params({"pipeline": [{"detector": "median"}]})
    with pytest.raises(ParameterError, match="not valid JSON"):
        parse_pipeline_params("{")
    for bad in (300, -1):  # LAS classes are 0-255
        with pytest.raises(ParameterError, match=r"reference_classes\[0\]: "):
            parse_pipeline_params({"reference_classes": [bad]})
    with pytest.raises(ParameterError, match="appears twice"):
        resolve_stages(PipelineParams(pipeline=[{"detector": "patch"}, {"detector": "patch"}]),
                       None)
    xyz, t, _ = spiky
    src = write_las(tmp_path / "in.las", xyz, gps_time=t, point_format=1)
    with pytest.raises(ParameterError, match="noise_class 40 does not fit point format 1"):
        process_file(src, tmp_path / "out.las", {"noise_class": 40})
    assert not (tmp_path / "out.las").exists()


def _two_scanner_file(tmp_path, rng, name, shuffle=False):
    xyz, t, spiked = scan_line_cloud(6000, rng, spikes=40, spike_size=0.5)
    psid = np.where(np.arange(6000) % 3 == 0, 1, 2).astype(np.uint16)  # interleaved scanners
    cls = np.where(spiked, 7, 1).astype(np.uint8)
    order = rng.permutation(6000) if shuffle else np.arange(6000)
    return write_las(tmp_path / name, xyz[order], gps_time=t[order], point_source_id=psid[order],
                     classification=cls[order], point_format=6)


def test_temporal_only_pipeline_streams_and_matches_the_in_memory_run(tmp_path, rng):
    src = _two_scanner_file(tmp_path, rng, "ordered.las")
    params = PipelineParams.model_validate(
        {"pipeline": [{"detector": "temporal", "sigma": 0.003, "max_gap": 0.01}],
         "reference_classes": [7], "noise_class": 18}
    )
    stats = process_file(src, tmp_path / "out.las", params, chunk_points=700, streaming=True)
    assert stats["mode"] == "streaming"
    out = laspy.read(tmp_path / "out.las")
    memory = run_pipeline(lasio.read_cloud(src), params)
    np.testing.assert_array_equal(out.outlier_flags, memory.flags)
    np.testing.assert_array_equal(out.temporal_score, memory.scores["temporal"])
    np.testing.assert_array_equal(out.classification, memory.classification)
    assert stats["overall"] == memory.statistics["overall"]
    assert stats["stages"][0]["points_tested"] == memory.statistics["stages"][0]["points_tested"]
    assert stats["stages"][0]["confusion"]["outliers_identified"] >= 35


def test_temporal_alone_streams_a_file_too_large_to_run_whole(tmp_path, rng, monkeypatch):
    # Beyond WHOLE_CLOUD_POINTS other pipelines run in tiles; temporal alone streams instead.
    import lidar_outliers.process

    src = _two_scanner_file(tmp_path, rng, "ordered.las")
    params = {"pipeline": [{"detector": "temporal", "sigma": 0.003}]}
    whole = process_file(src, tmp_path / "whole.las", params)
    assert whole["mode"] == "in memory"
    monkeypatch.setattr(lidar_outliers.process, "WHOLE_CLOUD_POINTS", 5000)  # the file: 6000
    streamed = process_file(src, tmp_path / "streamed.las", params, chunk_points=700)
    assert streamed["mode"] == "streaming"
    a, b = laspy.read(tmp_path / "whole.las"), laspy.read(tmp_path / "streamed.las")
    np.testing.assert_array_equal(a.outlier_flags, b.outlier_flags)
    assert np.sum(a.outlier_flags) > 0


def test_unordered_file_falls_back_to_memory(tmp_path, rng):
    src = _two_scanner_file(tmp_path, rng, "shuffled.las", shuffle=True)
    stats = process_file(src, tmp_path / "out.las",
                         {"pipeline": [{"detector": "temporal", "sigma": 0.003}]}, chunk_points=700,
                         streaming=True)
    assert stats["mode"] == "in memory" and "not in time order" in stats["streaming"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.las", "shuffled.las"]
    assert np.asarray(laspy.read(tmp_path / "out.las").outlier_flags).sum() > 0


def test_transient_leaves_points_without_a_time_untested(tmp_path):
    # a NaN or infinite gps_time cannot be placed on a scan line: those points are untested
    # and the others get what they get without them
    from tests.lasfiles import STREET_TRANSIENT, street_scene

    cloud = lasio.read_cloud(street_scene(tmp_path / "street.las"))
    params = PipelineParams.model_validate({"pipeline": [STREET_TRANSIENT]})
    gps_time = cloud.gps_time.copy()
    bad = np.array([5, 700, 1500])
    gps_time[bad] = [np.nan, np.inf, -np.inf]
    broken = Cloud(xyz=cloud.xyz, origin=cloud.origin, gps_time=gps_time,
                   point_source_id=cloud.point_source_id, classification=cloud.classification,
                   intensity=cloud.intensity)
    result = run_pipeline(broken, params)
    keep = np.setdiff1d(np.arange(len(cloud)), bad)
    alone = run_pipeline(cloud.subset(keep), params)
    score = result.scores["transient"]
    assert np.isnan(score[bad]).all() and not result.flags[bad].any()
    np.testing.assert_array_equal(score[keep], alone.scores["transient"])
    np.testing.assert_array_equal(result.flags[keep], alone.flags)
    assert result.flags.any()
    stage = result.statistics["stages"][0]
    assert stage["info"]["points_without_time"] == 3
    assert stage["points_tested"] == len(cloud) - 3


def _noise_free_file(tmp_path, name="clean.las"):
    """A straight drive over a tilted plane, recorded at the LAS millimetre and nothing else:
    every residual is the coordinates' rounding."""
    n = 6000
    t = 1000.0 + np.arange(n) * 1e-4
    along = np.arange(n) * 0.01
    across = 2.5 + 2.5 * np.sin(np.arange(n) * 0.02)  # a smooth sweep
    xyz = np.c_[500_000.0 + along, 5_000_000.0 + across, 100.0 + 0.02 * along + 0.1 * across]
    return write_las(tmp_path / name, xyz, gps_time=t, point_format=1,
                     offsets=(500_000.0, 5_000_000.0, 0.0))


@pytest.mark.parametrize("streaming", [False, True])
def test_auto_sigma_never_goes_below_the_coordinates_rounding(tmp_path, streaming):
    src = _noise_free_file(tmp_path)
    stats = process_file(src, tmp_path / "t.las", {"pipeline": [{"detector": "temporal"}]},
                         streaming=streaming)
    info = stats["stages"][0]["info"]
    rounding = 0.001 / np.sqrt(12.0)
    assert min(info["sigma"].values()) >= rounding * (1 - 1e-12)
    assert info["sigma_source"].endswith("raised to the coordinates' rounding")
    assert stats["stages"][0]["points_flagged"] == 0
    stats = process_file(src, tmp_path / "h.las", {"pipeline": [{"detector": "height_field"}]})
    info = stats["stages"][0]["info"]
    assert info["sigma"] >= rounding * (1 - 1e-12) and stats["stages"][0]["points_flagged"] == 0


def test_sigma_floor_of_temporal_streamed_before_tiles_equals_whole(tmp_path):
    src = _noise_free_file(tmp_path)
    pipeline = {"pipeline": [{"detector": "temporal"}, {"detector": "height_field", "low": False}]}
    whole = process_file(src, tmp_path / "whole.las", pipeline)
    tiled = process_file(src, tmp_path / "tiled.las", pipeline, tile_size=15.0)
    assert tiled["mode"] == "tiled"
    a, b = whole["stages"][0]["info"], tiled["stages"][0]["info"]
    assert a["sigma"] == b["sigma"] and min(a["sigma"].values()) >= 0.001 / np.sqrt(12.0) * (
        1 - 1e-12)
    assert b["sigma_source"].endswith("raised to the coordinates' rounding")
    assert whole["overall"] == tiled["overall"]


def test_height_field_sigma_floor_holds_estimated_and_given_sigma():
    from algorithms.height_field import detect_height_field

    g = np.stack(np.meshgrid(np.arange(40), np.arange(40)), -1).reshape(-1, 2) * 0.1
    plane = np.c_[g, 0.1 * g[:, 0]]  # exact: every residual is float rounding
    res = detect_height_field(plane, sigma_floor=0.001)
    assert res.info["sigma"] == 0.001 and not res.flagged.any()
    assert res.info["sigma_source"] == "auto, raised to the coordinates' rounding"
    given = detect_height_field(plane, sigma=1e-9, sigma_floor=0.001)
    assert given.info["sigma"] == 0.001 and not given.flagged.any()
    spiked = plane.copy()
    spiked[500, 2] += 0.05  # 50 floors up
    assert detect_height_field(spiked, sigma_floor=0.001).flagged[500]


def test_sigma_floor_tiled_equals_whole(tmp_path):
    src = _noise_free_file(tmp_path)
    pipeline = {"pipeline": [{"detector": "height_field"}]}
    whole = process_file(src, tmp_path / "whole.las", pipeline)
    tiled = process_file(src, tmp_path / "tiled.las", pipeline, tile_size=15.0)
    assert tiled["mode"] == "tiled" and whole["mode"] == "in memory"
    a, b = laspy.read(tmp_path / "whole.las"), laspy.read(tmp_path / "tiled.las")
    np.testing.assert_array_equal(a.outlier_flags, b.outlier_flags)
    np.testing.assert_allclose(a.height_field_score, b.height_field_score, rtol=1e-5,
                               atol=1e-5)

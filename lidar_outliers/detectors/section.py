"""``section``: one quadric per square XY section, refitted until no outlier remains (the
paper's algorithm (c); :mod:`algorithms.section`)."""

from __future__ import annotations

from algorithms.result import DetectorResult
from algorithms.section import SectionParameters
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector


def run(cloud: Cloud, params: SectionParameters) -> DetectorResult:
    from algorithms.section import detect_section

    return detect_section(
        cloud.xyz, section_size=params.section_size, sigma=params.sigma, alpha=params.alpha,
        max_iterations=params.max_iterations, anchor=cloud.anchor,
    )


DETECTOR = Detector(
    name="section",
    parameters=SectionParameters,
    run=run,
    summary="One quadric per square XY section, refitted until no outlier remains.",
    flag_bit=4,
    halo=lambda params: params.section_size,  # a section touching the tile lies within it
)

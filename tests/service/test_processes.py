"""Process descriptions and inputs come from the pydantic models of lidar_outliers/params.py."""

from __future__ import annotations

import pytest
from pydantic_core import to_jsonable_python

from lidar_outliers.detectors import DETECTORS
from lidar_outliers.params import PipelineParams, stage
from service.problems import Problem
from service.processes import describe, process_ids, resolve_inputs


def test_one_process_per_registered_detector_plus_pipeline() -> None:
    assert process_ids() == [*DETECTORS, "pipeline"]


@pytest.mark.parametrize("name", list(DETECTORS))
def test_description_has_every_parameter_with_its_default(name: str) -> None:
    doc = describe(name)
    model = DETECTORS[name].model
    for field, info in model.model_fields.items():
        if field != "detector":
            # The description is JSON: a tuple default (dror/snow origin) appears as a list.
            assert doc["inputs"][field]["schema"].get("default") == to_jsonable_python(
                info.default)
            assert doc["inputs"][field]["description"] == info.description
    for field in ("classify", "noise_class", "reference_classes"):
        assert field in doc["inputs"]
    assert doc["id"] == name and "async-execute" in doc["jobControlOptions"]


def test_detector_inputs_become_a_one_stage_pipeline() -> None:
    params = resolve_inputs("temporal", {"n1": 3, "sigma": 0.02, "classify": False})
    assert params == PipelineParams(pipeline=[stage("temporal", n1=3, sigma=0.02)], classify=False)


def test_pipeline_inputs_are_pipeline_params() -> None:
    doc = {"pipeline": [{"detector": "temporal"}, {"detector": "patch", "k": 50}],
           "noise_class": 18}
    assert resolve_inputs("pipeline", doc) == PipelineParams.model_validate(doc)


@pytest.mark.parametrize(
    ("process", "inputs", "named"),
    [("temporal", {"n1": 0}, "n1"), ("temporal", {"detector": "patch"}, "detector"),
     ("temporal", {"max_gap": -1.0}, "max_gap"), ("patch", {"k": 5}, "k"),
     ("pipeline", {"pipeline": []}, "pipeline"), ("ground", {"bogus": 1}, "bogus")],
)
def test_bad_inputs_name_the_parameter(process: str, inputs: dict, named: str) -> None:
    with pytest.raises(Problem) as caught:
        resolve_inputs(process, inputs)
    assert caught.value.status == 422 and named in caught.value.detail


def test_unknown_process_is_404() -> None:
    with pytest.raises(Problem) as caught:
        describe("nope")
    assert caught.value.status == 404 and caught.value.slug == "no-such-process"

"""The committed OpenAPI document matches the app; regenerate with `slloc openapi`."""

from pathlib import Path

from app.openapi import openapi_document

COMMITTED = Path(__file__).resolve().parents[1] / "openapi" / "openapi.json"


def test_openapi_is_up_to_date() -> None:
    assert COMMITTED.read_text() == openapi_document(), (
        "openapi/openapi.json is stale: run `slloc openapi` and commit the result"
    )


def test_every_error_is_documented_as_problem_json() -> None:
    import json

    doc = json.loads(COMMITTED.read_text())
    for path, operations in doc["paths"].items():
        for method, operation in operations.items():
            for status, response in operation["responses"].items():
                if status.startswith(("4", "5")):
                    assert "application/problem+json" in response["content"], (method, path, status)


def test_json_form_fields_and_enums_are_published() -> None:
    import json

    from services.estimators.base import FailureReason
    from services.estimators.registry import estimator_names

    doc = json.loads(COMMITTED.read_text())
    schemas = doc["components"]["schemas"]
    for body, field, model in (
        ("Body_add_image", "metadata", "ImageMetadata"),
        ("Body_localize", "params", "LocalizeParamsIn"),
    ):
        form_field = schemas[body]["properties"][field]
        assert form_field["contentMediaType"] == "application/json"
        assert form_field["contentSchema"] == {"$ref": f"#/components/schemas/{model}"}
        assert schemas[model]["type"] == "object"
    assert set(schemas["ImageMetadata"]["required"]) == {"name", "camera", "cam_from_world"}
    assert "top_k" in schemas["LocalizeParamsIn"]["properties"]

    assert schemas["EstimatorName"]["enum"] == estimator_names()
    assert schemas["FailureReason"]["enum"] == [reason.value for reason in FailureReason]
    result = schemas["LocalizeResult"]["properties"]
    assert result["estimator"]["$ref"] == "#/components/schemas/EstimatorName"
    assert {"$ref": "#/components/schemas/FailureReason"} in result["reason"]["anyOf"]
    estimator_param = schemas["LocalizeParamsIn"]["properties"]["estimator"]
    assert {"$ref": "#/components/schemas/EstimatorName"} in estimator_param["anyOf"]

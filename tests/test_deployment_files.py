"""The deployment files parse and hold what the README promises: the Kubernetes manifests are
valid against the Kubernetes OpenAPI schemas shipped by ``kubernetes-validate`` (offline, strict:
unknown fields are errors), the compose file runs N API replicas behind nginx on PostgreSQL."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "deploy" / "k8s"
KUBERNETES_VERSION = "1.30.0"


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
    for probe in ("readinessProbe", "livenessProbe"):
        assert container[probe]["httpGet"]["path"] == "/v1/health"
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


def test_compose_runs_replicas_behind_a_proxy_on_postgres() -> None:
    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    services = compose["services"]
    api = services["api"]
    assert "replicas" in api["deploy"] and "ports" not in api  # replicas share no host port
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

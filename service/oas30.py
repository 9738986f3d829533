"""JSON Schema (draft 2020-12, as pydantic and FastAPI write it) down to OpenAPI 3.0 schema
objects, for the two places OGC API - Processes 1.0 wants 3.0: the API definition of the
``oas30`` conformance class (FastAPI writes OpenAPI 3.1) and the input schemas of process
descriptions (the standard's ``schema.yaml`` is a 3.0 schema object).

The rewrites: ``null`` among the types or in ``anyOf`` / ``oneOf`` becomes ``nullable``;
``const`` a one-value ``enum``; numeric ``exclusiveMinimum`` / ``exclusiveMaximum`` the bound
plus the boolean flag; ``examples`` the first ``example``; ``prefixItems`` (tuples) ``items``
with the length; a ``$ref`` with siblings an ``allOf`` of it. Keywords 3.0 does not know are
dropped.
"""

from __future__ import annotations

import copy
from typing import Any

#: Keywords of an OpenAPI 3.0 schema object.
OAS30_KEYS = frozenset({
    "title", "multipleOf", "maximum", "exclusiveMaximum", "minimum", "exclusiveMinimum",
    "maxLength", "minLength", "pattern", "maxItems", "minItems", "uniqueItems",
    "maxProperties", "minProperties", "required", "enum", "type", "allOf", "oneOf", "anyOf",
    "not", "items", "properties", "additionalProperties", "description", "format", "default",
    "nullable", "discriminator", "readOnly", "writeOnly", "xml", "externalDocs", "example",
    "deprecated", "$ref",
})
#: Keywords of the schema of an input or output in a process description (``schema.yaml``).
OGC_KEYS = (OAS30_KEYS - {"discriminator", "xml", "externalDocs"}) | {
    "contentMediaType", "contentEncoding", "contentSchema"}
SCHEMA_LISTS = ("allOf", "oneOf", "anyOf")
HTTP_METHODS = ("get", "put", "post", "delete", "options", "head", "patch", "trace")


class Downgrade:
    """One conversion: ``ogc`` selects the process-description dialect (references inlined
    from ``defs``, content keywords kept); otherwise OpenAPI 3.0 with component references."""

    def __init__(self, *, ogc: bool = False, defs: dict[str, Any] | None = None) -> None:
        self.ogc = ogc
        self.defs = defs or {}
        self.keys = OGC_KEYS if ogc else OAS30_KEYS

    def schema(self, node: Any, seen: tuple[str, ...] = ()) -> Any:
        if not isinstance(node, dict):
            return node
        node = dict(node)
        node.pop("$defs", None)
        ref = node.get("$ref")
        if isinstance(ref, str) and ref.startswith("#/$defs/"):
            name = ref.removeprefix("#/$defs/")
            if self.ogc and name in self.defs and name not in seen:
                del node["$ref"]
                target = self.schema(self.defs[name], (*seen, name))
                return self.schema({**target, **node}, seen) if node else target
            node["$ref"] = "#/components/schemas/" + name
        if "$ref" in node and len(node) > 1:
            node = {"allOf": [{"$ref": node.pop("$ref")}], **node}
        out: dict[str, Any] = {}
        nullable = False
        for key, value in node.items():
            if key == "const":
                out["enum"] = [value]
            elif key == "type" and isinstance(value, list):
                types = [t for t in value if t != "null"]
                nullable |= len(types) < len(value)
                if len(types) == 1:
                    out["type"] = types[0]
                elif types:
                    out.setdefault("anyOf", []).extend({"type": t} for t in types)
            elif key == "type" and value == "null":
                nullable = True
            elif key in SCHEMA_LISTS:
                branches = [b for b in value if not (isinstance(b, dict) and b == {"type": "null"})]
                nullable |= len(branches) < len(value)
                converted = [self.schema(b, seen) for b in branches]
                if len(converted) == 1 and key != "allOf":
                    only = converted[0]
                    out.update(only if "$ref" not in only else {"allOf": [only]})
                elif converted:
                    out[key] = converted
            elif key in ("exclusiveMinimum", "exclusiveMaximum") and not isinstance(value, bool):
                out["minimum" if key == "exclusiveMinimum" else "maximum"] = value
                out[key] = True
            elif key == "examples" and isinstance(value, list) and value:
                out.setdefault("example", value[0])
            elif key == "prefixItems":
                items = [self.schema(v, seen) for v in value]
                out["items"] = items[0] if all(i == items[0] for i in items) else {"anyOf": items}
                out.setdefault("minItems", len(items))
                out.setdefault("maxItems", len(items))
            elif key in ("items", "not"):
                out[key] = self.schema(value, seen) if isinstance(value, dict) else {}
            elif key == "additionalProperties":
                out[key] = self.schema(value, seen) if isinstance(value, dict) else value
            elif key == "properties":
                out[key] = {k: self.schema(v, seen) for k, v in value.items()}
            elif key == "discriminator" and not self.ogc:
                mapping = {k: v.replace("#/$defs/", "#/components/schemas/")
                           for k, v in value.get("mapping", {}).items()}
                out[key] = {**value, **({"mapping": mapping} if mapping else {})}
            elif key in ("contentMediaType", "contentEncoding") and not self.ogc:
                if value in ("binary", "application/octet-stream") and node.get("type") == "string":
                    out.setdefault("format", "binary")
            elif key in self.keys or (not self.ogc and key.startswith("x-")):
                out.setdefault(key, value)
        if nullable:
            out["nullable"] = True
        return out


def process_input_schema(schema: dict[str, Any], defs: dict[str, Any]) -> dict[str, Any]:
    """One input's schema, as the standard's ``schema.yaml`` has it (references inlined)."""
    return Downgrade(ogc=True, defs=defs).schema(schema)


def _media(content: dict[str, Any], convert: Downgrade) -> None:
    for media in content.values():
        if isinstance(media, dict) and "schema" in media:
            media["schema"] = convert.schema(media["schema"])


def _operation(op: dict[str, Any], convert: Downgrade) -> None:
    for parameter in op.get("parameters", []):
        if "schema" in parameter:
            parameter["schema"] = convert.schema(parameter["schema"])
    _media(op.get("requestBody", {}).get("content", {}), convert)
    for response in op.get("responses", {}).values():
        _media(response.get("content", {}), convert)
        for header in response.get("headers", {}).values():
            if "schema" in header:
                header["schema"] = convert.schema(header["schema"])


def _unique_id(op: dict[str, Any], method: str, seen: set[str]) -> None:
    """A route answering several methods (GET and HEAD) gets one operationId from FastAPI;
    OpenAPI wants them unique."""
    op_id = op.get("operationId")
    if op_id is None:
        return
    while op_id in seen:
        op_id = f"{op_id}_{method}"
    op["operationId"] = op_id
    seen.add(op_id)


def openapi_30(document: dict[str, Any]) -> dict[str, Any]:
    """A copy of an OpenAPI 3.1 document written by FastAPI, as OpenAPI 3.0.3."""
    doc = copy.deepcopy(document)
    convert = Downgrade()
    doc["openapi"] = "3.0.3"
    for key in ("webhooks", "jsonSchemaDialect"):
        doc.pop(key, None)
    doc.get("info", {}).pop("summary", None)
    doc.get("info", {}).get("license", {}).pop("identifier", None)
    seen: set[str] = set()
    for item in doc.get("paths", {}).values():
        for parameter in item.get("parameters", []):
            if "schema" in parameter:
                parameter["schema"] = convert.schema(parameter["schema"])
        for method in HTTP_METHODS:
            if method in item:
                _operation(item[method], convert)
                _unique_id(item[method], method, seen)
    components = doc.get("components", {})
    components["schemas"] = {k: convert.schema(v)
                             for k, v in components.get("schemas", {}).items()}
    for parameter in components.get("parameters", {}).values():
        if "schema" in parameter:
            parameter["schema"] = convert.schema(parameter["schema"])
    for response in components.get("responses", {}).values():
        _media(response.get("content", {}), convert)
    for body in components.get("requestBodies", {}).values():
        _media(body.get("content", {}), convert)
    return doc

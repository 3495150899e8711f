"""The OpenAPI schema as the server answers: FastAPI's generated one, less what never happens.

FastAPI documents a 422 ``HTTPValidationError`` (``{"detail": [...]}``) on every route with
parameters. This server answers validation errors with its own body (``ErrorResponse``) and
documents the 422s that can happen itself, so the generated ones go, with their schemas.
"""

from __future__ import annotations

import json
from typing import Any

from fastapi import FastAPI

_DEFAULT_422 = "#/components/schemas/HTTPValidationError"


def _drop_default_422(schema: dict[str, Any]) -> None:
    for path in schema.get("paths", {}).values():
        for operation in path.values():
            responses = operation.get("responses", {})
            if _DEFAULT_422 in json.dumps(responses.get("422", {})):
                del responses["422"]
    if "HTTPValidationError" not in json.dumps(schema.get("paths", {})):
        schemas = schema.get("components", {}).get("schemas", {})
        schemas.pop("HTTPValidationError", None)
        if "#/components/schemas/ValidationError" not in json.dumps(schemas):
            schemas.pop("ValidationError", None)


def install_openapi(app: FastAPI) -> None:
    """Make ``app.openapi()`` (and ``/openapi.json``, ``/docs``) serve the truthful schema."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            _drop_default_422(generate())
        return app.openapi_schema

    app.openapi = openapi

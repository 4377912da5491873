"""What every answer of the API looks like: JSON errors for unknown ``/v1`` paths (404) and wrong methods (405),
validation errors as ``ErrorOut`` (a sentence plus the details), security headers on every response, and an
OpenAPI document that says so (401 on every route that needs a key, 422 as ``ErrorOut``)."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DataError
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

SECURITY_HEADERS: list[tuple[bytes, bytes]] = [
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
    (b"cross-origin-opener-policy", b"same-origin"),
    (b"permissions-policy", b"camera=(), microphone=(), geolocation=()"),
]
PAGE_CSP = (b"content-security-policy",
            b"default-src 'self'; script-src 'self' 'wasm-unsafe-eval'; style-src 'self' 'unsafe-inline'; "
            b"img-src 'self' data: blob:; connect-src 'self' data: blob:; worker-src 'self' blob:; "
            b"object-src 'none'; base-uri 'none'; frame-ancestors 'none'")


class SecurityHeaders:
    """ASGI middleware: security headers on every response; a Content-Security-Policy on the front end."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        page = not scope["path"].startswith(("/v1", "/docs", "/redoc", "/openapi.json"))

        async def wrapped(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                present = {k.lower() for k, _ in headers}
                extra = SECURITY_HEADERS + ([PAGE_CSP] if page else [])
                headers.extend((k, v) for k, v in extra if k not in present)
                message["headers"] = headers
            await send(message)

        await self.app(scope, receive, wrapped)


def _sentence(errors: list[dict[str, Any]]) -> str:
    parts = []
    for e in errors[:5]:
        loc = ".".join(str(p) for p in e.get("loc", ()) if p not in ("body", "query", "path", "header"))
        parts.append(f"{loc or 'request'}: {e.get('msg', 'invalid')}")
    more = f" (and {len(errors) - 5} more)" if len(errors) > 5 else ""
    return "invalid request: " + "; ".join(parts) + more


async def validation_error(_: Request, exc: Exception) -> JSONResponse:
    """422 as ErrorOut: a sentence naming each problem, and the details in ``errors``."""
    assert isinstance(exc, RequestValidationError)
    errors = [{"loc": [str(p) for p in e.get("loc", ())], "msg": str(e.get("msg", "")), "type": str(e.get("type", ""))}
              for e in exc.errors()]
    return JSONResponse({"detail": _sentence(errors), "errors": errors}, status_code=422)


async def data_error(_: Request, exc: Exception) -> JSONResponse:
    """422 for a value the database refuses to store or compare (a NUL character in a text, for example): the
    request's fault, not the server's."""
    return JSONResponse({"detail": "a value in the request cannot be used (for example a NUL character in a text "
                                   "or a name); remove it and try again"}, status_code=422)


def add_v1_fallback(app: FastAPI) -> None:
    """Unknown paths under /v1 answer JSON 404, and known paths with another method JSON 405 (instead of the
    front end's page)."""

    methods = ["GET", "POST", "PUT", "PATCH", "DELETE", "HEAD", "OPTIONS"]

    @app.api_route("/v1/{rest:path}", methods=methods, include_in_schema=False)
    async def v1_fallback(request: Request, rest: str) -> JSONResponse:
        path = request.url.path
        allowed = []
        for method in methods:
            probe = {**request.scope, "method": method}
            for route in app.router.routes:
                # the front end's mount at / matches every path and method: not an API route
                if getattr(route, "name", None) in ("v1_fallback", "frontend"):
                    continue
                if route.matches(probe)[0] == Match.FULL:
                    allowed.append(method)
                    break
        if allowed:
            return JSONResponse({"detail": f"{request.method} is not allowed on {path}; use {', '.join(allowed)}"},
                                status_code=405, headers={"Allow": ", ".join(allowed)})
        return JSONResponse({"detail": f"no such API path: {path[:200]}"}, status_code=404)


_MALFORMED_BODY = {"description": "The body could not be read (not UTF-8, or a malformed multipart body)",
                   "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"}}}}


def _runtime_bounds(op: dict[str, Any], max_offset: int) -> None:
    """The limits the server checks at run time, written into an operation's parameters."""
    for param in op.get("parameters", []):
        if param.get("in") == "query" and param.get("name") == "offset":
            schema = param.setdefault("schema", {})
            schema["maximum"] = min(schema.get("maximum", max_offset), max_offset)


def true_openapi(app: FastAPI) -> dict[str, Any]:
    """The OpenAPI document with 401 on every operation that needs a key, 400 on every one with a body, every
    422 as ErrorOut, and the run-time limits of this process's settings."""
    if app.openapi_schema:
        return app.openapi_schema
    doc = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes,
                      tags=app.openapi_tags)
    error = {"$ref": "#/components/schemas/ErrorOut"}
    max_offset = app.state.settings.max_list_offset
    for ops in doc.get("paths", {}).values():
        for op in ops.values():
            if not isinstance(op, dict) or "responses" not in op:
                continue
            responses = op["responses"]
            if any("APIKeyHeader" in req for req in op.get("security", [])):
                responses.setdefault("401", {"description": "Missing, unknown or revoked API key",
                                             "content": {"application/json": {"schema": error}}})
            if "requestBody" in op:
                responses.setdefault("400", _MALFORMED_BODY)
            if "422" in responses:
                responses["422"]["content"] = {"application/json": {"schema": error}}
            _runtime_bounds(op, max_offset)
    schemas = doc.setdefault("components", {}).setdefault("schemas", {})
    schemas.pop("HTTPValidationError", None)
    schemas.pop("ValidationError", None)
    app.openapi_schema = doc
    return doc


def install(app: FastAPI) -> None:
    """Wire all of the above into ``app`` (after its routers, before the front end is mounted)."""
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_exception_handler(DataError, data_error)
    add_v1_fallback(app)
    app.openapi = lambda: true_openapi(app)  # type: ignore[method-assign]
    app.add_middleware(SecurityHeaders)

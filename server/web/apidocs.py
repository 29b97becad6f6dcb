"""The API's interactive docs (Swagger UI at `/docs`, ReDoc at `/redoc`) from local files.

FastAPI's default pages load their scripts from a CDN, which leaves them blank offline or behind
a strict firewall. The dashboard's npm dependencies include both bundles (`make client`); when
they are missing the pages say how to get them, and `/openapi.json` always works.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse

SWAGGER = "node_modules/swagger-ui-dist"
REDOC = "node_modules/redoc/bundles/redoc.standalone.js"


def _missing(client_dir: Path, what: str) -> HTMLResponse:
    return HTMLResponse(
        f"<!doctype html><title>scalesteer API</title><p>{what} is not installed next to the "
        f"dashboard ({client_dir}/node_modules). Run <code>make client</code> (npm ci in "
        "client_web), or read the API description at <a href='/openapi.json'>/openapi.json</a>."
        "</p>",
        status_code=503,
    )


def add_docs(app: FastAPI, client_dir: Path) -> None:
    """Serve `/docs` and `/redoc` from the dashboard's own copies of their scripts (the
    dashboard's static files are mounted at `/`)."""
    title = f"{app.title} API"

    @app.get("/docs", include_in_schema=False)
    async def swagger() -> HTMLResponse:
        if not (client_dir / SWAGGER / "swagger-ui-bundle.js").is_file():
            return _missing(client_dir, "Swagger UI")
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=title,
            swagger_js_url=f"/{SWAGGER}/swagger-ui-bundle.js",
            swagger_css_url=f"/{SWAGGER}/swagger-ui.css",
            swagger_favicon_url="/favicon.svg",
        )

    @app.get("/redoc", include_in_schema=False)
    async def redoc() -> HTMLResponse:
        if not (client_dir / REDOC).is_file():
            return _missing(client_dir, "ReDoc")
        return get_redoc_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=title,
            redoc_js_url=f"/{REDOC}",
            redoc_favicon_url="/favicon.svg",
            with_google_fonts=False,
        )

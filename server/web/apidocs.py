"""The API's interactive docs (Swagger UI at `/docs`, ReDoc at `/redoc`) from local files.

FastAPI's default pages load their scripts from a CDN, which leaves them blank offline or behind
a strict firewall. The dashboard's npm dependencies include both bundles (`make client`); when
they are missing the pages say how to get them, and `/openapi.json` always works.

The API description declares the token (`server.web.access.BEARER`), so Swagger UI has an
Authorize button; `/docs?token=...` (the dashboard's link with `/docs` for its path) is
authorized with that token as it opens, so "Try it out" works at once.
"""

from __future__ import annotations

import json
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html
from fastapi.responses import HTMLResponse

from server.web.access import BEARER

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
        return HTMLResponse(_swagger_page(app.openapi_url or "/openapi.json", title))

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


def _swagger_page(openapi_url: str, title: str) -> str:
    """Swagger UI from the local bundle, authorized with the page's `?token=` once loaded (the
    token never leaves the page but in the calls' Authorization header)."""
    scheme = json.dumps(BEARER.scheme_name)
    return f"""<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="stylesheet" href="/{SWAGGER}/swagger-ui.css">
<link rel="icon" href="/favicon.svg">
<title>{title}</title>
</head>
<body>
<div id="swagger-ui"></div>
<script src="/{SWAGGER}/swagger-ui-bundle.js"></script>
<script>
const token = new URLSearchParams(window.location.search).get("token");
window.ui = SwaggerUIBundle({{
  url: {json.dumps(openapi_url)},
  dom_id: "#swagger-ui",
  layout: "BaseLayout",
  deepLinking: true,
  persistAuthorization: false,
  presets: [SwaggerUIBundle.presets.apis, SwaggerUIBundle.SwaggerUIStandalonePreset],
  onComplete: () => {{
    if (token) window.ui.preauthorizeApiKey({scheme}, token);
  }},
}});
</script>
</body>
</html>
"""

"""Who may call a REST route, decided from the request's headers alone.

The checks are FastAPI dependencies (so the API description names them), and `GatedRoute` runs
them again before FastAPI reads the request's body: a caller without the right token, or a
viewer over its render budget, is answered at once instead of after an upload of hundreds of
megabytes has been received and spooled. Each check keeps its verdict in the request's scope, so
running twice costs nothing and charges a budget once.
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.responses import Response

import protocol as p
from server.web.auth import token_role
from server.web.spool import SpoolingRequest
from server.web.state import AppState

_ROLE = "scalesteer.role"
_CHARGED = "scalesteer.render_charged"
BEARER = HTTPBearer(
    scheme_name="token",
    description="The server token (every route), or the viewer token (reading and rendering); "
    "`?token=` in the address works too.",
    auto_error=False,
)
"""Declares the token to the API description, so `/docs` has an Authorize button; the token
itself is checked below, from the headers (`request_token`)."""
Token = Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)]


def app_state(request: Request) -> AppState:
    state: AppState = request.app.state.scalesteer
    return state


def request_token(request: Request) -> str | None:
    """The token of a REST call: `Authorization: Bearer`, `X-Scalesteer-Token` or `?token=`."""
    auth = request.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return request.headers.get("x-scalesteer-token") or request.query_params.get("token")


def viewer_access(request: Request, _token: Token = None) -> p.Role:
    """Any valid token (401 without one); the role it carries."""
    role: p.Role | None = request.scope.get(_ROLE)
    if role is None:
        role = token_role(app_state(request).settings, request_token(request))
        if role is None:
            raise HTTPException(
                401, "missing or wrong token (Authorization: Bearer TOKEN or ?token=)"
            )
        request.scope[_ROLE] = role
    return role


def steerer_access(request: Request, _token: Token = None) -> p.Role:
    """The server token (403 for the read-only viewer token)."""
    role = viewer_access(request)
    if role != "steerer":
        raise HTTPException(403, "this needs the server token; the viewer token is read-only")
    return role


def render_access(request: Request, _token: Token = None) -> p.Role:
    """Any valid token; a viewer-token holder's call is charged to the viewers' shared render
    budget (429 with `Retry-After` when it is spent)."""
    role = viewer_access(request)
    if role != "viewer" or request.scope.get(_CHARGED):
        return role
    request.scope[_CHARGED] = True
    state = app_state(request)
    if not state.viewer_renders.allow():
        wait = state.viewer_renders.wait_s()
        raise HTTPException(
            429,
            f"renders with the viewer token are limited to "
            f"{state.settings.viewer_renders_per_min:g} a minute; retry in {wait:.0f} s",
            headers={"Retry-After": str(max(1, round(wait)))},
        )
    return role


HEADER_CHECKS: frozenset[Callable[..., p.Role]] = frozenset(
    {viewer_access, steerer_access, render_access}
)
"""Dependencies that need nothing but the request's headers: run before its body is read."""


class GatedRoute(APIRoute):
    """A route whose header checks (`HEADER_CHECKS` among its dependencies) run before its body
    is read, and whose uploads spool into the server's own directory (`SpoolingRequest`)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        checks = [d.call for d in self.dependant.dependencies if d.call in HEADER_CHECKS]

        async def gated(request: Request) -> Response:
            for check in checks:
                check(request)
            return await handler(SpoolingRequest(request.scope, request.receive))

        return gated

"""The server's REST API from Python: JSON calls, uploads, downloads; refusals as exceptions."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Mapping, Sequence
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import IO, Any

import httpx

from scalesteer.errors import ScalesteerError

TIMEOUT_S = 60.0

FormValue = str | int | float | bool | Mapping[str, Any] | Sequence[Any] | None
Files = Mapping[str, str | os.PathLike[str] | Sequence[str | os.PathLike[str]]]


class Rest:
    """HTTP calls to one server with its token (`Authorization: Bearer`)."""

    def __init__(self, url: str, token: str | None, timeout: float = TIMEOUT_S) -> None:
        headers = {"User-Agent": "scalesteer-python"}
        if token:
            headers["Authorization"] = f"Bearer {token}"
        self.url = url.rstrip("/")
        loopback = httpx.URL(self.url).host in ("127.0.0.1", "localhost", "::1")
        self._http = httpx.Client(
            base_url=self.url, headers=headers, timeout=timeout, trust_env=not loopback
        )
        self.closed = False

    def close(self) -> None:
        self.closed = True
        self._http.close()

    def check_open(self) -> None:
        """Raise `not_ready` once closed (`Client.close()`, `scalesteer.shutdown()`): httpx
        would say only that "the client has been closed"."""
        if self.closed:
            raise ScalesteerError("not_ready", f"this client of {self.url} is closed", "url")

    def request(
        self,
        method: str,
        path: str,
        *,
        json_body: Any = None,
        form: Mapping[str, FormValue] | None = None,
        files: Files | None = None,
        params: Mapping[str, Any] | None = None,
        timeout: float | None = None,
    ) -> httpx.Response:
        """One call; a 4xx/5xx answer raises `ScalesteerError` with the code its status
        stands for and the field its detail names."""
        self.check_open()
        with ExitStack() as stack:
            uploads = _open_files(stack, files or {})
            try:
                answer = self._http.request(
                    method,
                    path,
                    json=json_body,
                    data=_form(form) if form is not None else None,
                    files=uploads or None,
                    params=params,
                    timeout=timeout if timeout is not None else httpx.USE_CLIENT_DEFAULT,
                )
            except httpx.HTTPError as exc:
                raise ScalesteerError(
                    "not_ready", f"cannot reach {self.url}: {exc}", "url"
                ) from None
        check(answer)
        return answer

    def json(self, method: str, path: str, **kwargs: Any) -> Any:
        return self.request(method, path, **kwargs).json()

    @contextmanager
    def stream(self, path: str) -> Iterator[httpx.Response]:
        """A GET whose body is read in pieces (downloads)."""
        self.check_open()
        with self._http.stream("GET", path) as answer:
            if answer.status_code >= 400:
                answer.read()
            check(answer)
            yield answer

    def download(self, path: str, target: str | os.PathLike[str]) -> Path:
        """Save the body of GET `path` to `target` (written whole or not at all)."""
        target = Path(target)
        partial = target.with_name(target.name + ".part")
        with self.stream(path) as answer, open(partial, "wb") as out:
            for chunk in answer.iter_bytes(1 << 20):
                out.write(chunk)
        partial.replace(target)
        return target


def check(answer: httpx.Response) -> None:
    if answer.status_code < 400:
        return
    try:
        detail = answer.json().get("detail", answer.text)
    except (ValueError, AttributeError):
        detail = answer.text
    if not isinstance(detail, str):  # FastAPI's own validation errors: a list of problems
        detail = json.dumps(detail)[:2000]
    raise ScalesteerError.of_http(answer.status_code, detail or answer.reason_phrase)


def _form(fields: Mapping[str, FormValue]) -> dict[str, str]:
    out: dict[str, str] = {}
    for key, value in fields.items():
        if value is None:
            continue
        if isinstance(value, bool):
            out[key] = "true" if value else "false"
        elif isinstance(value, Mapping | list | tuple):
            out[key] = json.dumps(value)
        else:
            out[key] = str(value)
    return out


def _open_files(stack: ExitStack, files: Files) -> list[tuple[str, tuple[str, IO[bytes]]]]:
    out: list[tuple[str, tuple[str, IO[bytes]]]] = []
    for field, paths in files.items():
        many = [paths] if isinstance(paths, str | os.PathLike) else list(paths)
        for path in many:
            handle = stack.enter_context(open(path, "rb"))  # noqa: SIM115 (closed by the stack)
            out.append((field, (Path(path).name, handle)))
    return out

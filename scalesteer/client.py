"""The client of one render server: its sessions, REST calls and, when no URL is given, the
server itself (`LocalServer`)."""

from __future__ import annotations

import atexit
import contextlib
import os
import secrets
import threading
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, cast
from urllib.parse import parse_qs, urlencode, urlsplit, urlunsplit

from pydantic import ValidationError

from protocol import Camera, ErrorCode, Hello, RenderParams, Role
from scalesteer import background, images
from scalesteer.errors import ScalesteerError
from scalesteer.jobs import Job, Recording
from scalesteer.link import ViewLink
from scalesteer.local import LocalServer
from scalesteer.rest import Rest
from scalesteer.session import IDLE_VIEW, Session, checked_camera, checked_params, invalid

CLIENT_NAME = "scalesteer-python"

_default_lock = threading.Lock()
_default_server: LocalServer | None = None
_local_clients: weakref.WeakSet[Client] = weakref.WeakSet()
"""Clients of the process's own server: `shutdown()` closes them (and what feeds their
sessions) before the server stops, so no replay is left reconnecting to it."""


def default_server(device: str = "auto") -> LocalServer:
    """The server of this process's own, started on first use and ended with the process; a
    new one when it no longer answers. `device` other than `auto` must be the running one's:
    a client does not get another device's server without a word."""
    global _default_server
    if not isinstance(device, str):
        raise TypeError(f"device: a name such as 'cpu' or 'cuda:0', not {device!r}")
    with _default_lock:
        running = _default_server
        if running is not None and not running.answers():
            running.stop()  # whatever is left of it ends before another one starts
            running = None
        if running is None:
            _default_server = running = LocalServer(device)
        elif device not in ("auto", running.device):
            raise ValueError(
                f"this process's own server renders on {running.device!r}, not {device!r}: "
                "scalesteer.shutdown() it first to start one on another device"
            )
        return running


@dataclass(frozen=True)
class ServerLink:
    """What a server URL or a dashboard link names (`http://HOST:PORT/?token=...&session=...`,
    as `scalesteer serve` prints it; a read-only link adds `role=viewer`)."""

    url: str
    token: str | None
    session: str | None
    role: Role | None


def split_url(url: str) -> ServerLink:
    """The base URL, token, session and role a server URL or a dashboard link names."""
    parts = urlsplit(url if "://" in url else f"http://{url}")
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"a server URL looks like http://127.0.0.1:8000, got {url!r}")
    query = parse_qs(parts.query)
    token = query.get("token", [None])[0]
    session = query.get("session", [None])[0]
    role = query.get("role", [None])[0]
    if role not in (None, "steerer", "viewer"):
        raise ValueError(f"a dashboard link's role is steerer or viewer, got {role!r}")
    base = urlunsplit((parts.scheme, parts.netloc, "", "", ""))
    return ServerLink(base, token, session, cast("Role | None", role))


class Client:
    """A connection to a scalesteer render server.

    `url`: the server (`http://127.0.0.1:8000`) or a dashboard link holding the token; None
    starts a server of this process's own (`device`: auto, cpu or cuda:N), shared by every
    client of the process and ended with it. `token`: the server token (steer everything) or
    the viewer token (watch only); `role` `viewer` joins sessions read-only (default: the
    link's role, as a read-only dashboard link names it, else `steerer`)."""

    def __init__(
        self,
        url: str | None = None,
        token: str | None = None,
        *,
        role: Role | None = None,
        device: str = "auto",
        timeout: float = 30.0,
    ) -> None:
        self.local: LocalServer | None = None
        if url is None:
            self.local = default_server(device)
            base, token, self.default_session = self.local.url, self.local.token, None
            if not _local_clients:  # after the server's own: runs before the server stops
                atexit.register(_close_local_clients)
            _local_clients.add(self)
        else:
            link = split_url(url)
            base, self.default_session = link.url, link.session
            token = token if token is not None else link.token or os.environ.get("SCALESTEER_TOKEN")
            role = role or link.role
        self.url = base
        self.token = token
        self.role: Role = role or "steerer"
        self.timeout = timeout
        self.rest = Rest(base, token)
        self._sessions: list[Session] = []

    @property
    def ws_url(self) -> str:
        scheme = "wss" if self.url.startswith("https") else "ws"
        return f"{scheme}{self.url[self.url.index(':') :]}"

    # ------------------------------------------------------------------ sessions

    def session(self, name: str | None = None) -> Session:
        """Open (or join) the session `name` (default: the link's session, else `default`)."""
        self.rest.check_open()  # a closed client opens nothing
        name = name or self.default_session or "default"
        link = self.open_link(name, self.role, CLIENT_NAME)
        session = Session(self, link, self.timeout)
        background.run(link.view(IDLE_VIEW), self.timeout)
        self._sessions.append(session)
        return session

    def open_link(self, name: str, role: Role, client: str) -> ViewLink:
        """A WebSocket link to session `name` as `role`, naming itself `client`."""
        try:
            Hello(role=role, session=name)
        except ValidationError as exc:
            raise invalid(exc, "hello") from None
        link = ViewLink(f"{self.ws_url}/ws/view", self.token, name, role, client)
        background.run(link.open(), self.timeout + 20)
        return link

    def open(
        self,
        obj: Any,
        session: str | None = None,
        *,
        frame: int | None = None,
        fps: float = 10.0,
        loop: bool = False,
        paused: bool = False,
        interval: int = 100,
        steps: int | None = None,
        wait: float | None = 60.0,
        **options: Any,
    ) -> Session:
        """A session fed by `obj`: an MDAnalysis `Universe` or `AtomGroup`, an MDTraj
        `Trajectory` or ASE `Atoms` (or a list of them) are played as a trajectory (`frame`:
        that frame alone; `fps`, `loop`, `paused`); an OpenMM `Simulation` gets the steering
        reporter (a frame every `interval` steps; `steps`: run that many on a thread of its
        own). `session` names it (default: a new name). Waits up to `wait` seconds for the
        first frame. More `options` go to the adapter (`TrajectoryReplay`,
        `SteeringReporter`)."""
        from scalesteer import sources

        self.rest.check_open()
        if self.role == "viewer":  # it would join as a viewer, who cannot make a session
            raise ScalesteerError(
                ErrorCode.FORBIDDEN,
                "a viewer cannot open a session (it feeds one a simulation): connect with the "
                "server token, or join a session that runs with client.session(name)",
                "role",
            )
        kind = sources.kind_of(obj)
        name = session or f"{kind}-{secrets.token_hex(3)}"
        opened = self.session(name)
        sim_url = f"{self.ws_url}/ws/sim"
        try:
            if kind == "openmm":
                source = sources.OpenMMSource(
                    obj, sim_url, self.token, opened.name, interval=interval, **options
                )
                opened.source = source
                if steps:
                    source.run(steps)
                else:
                    wait = None  # no frame comes before the notebook steps it
            else:
                structure = sources.structure_of(obj, frame)
                opened.source = sources.ReplaySource(
                    structure, sim_url, self.token, opened.name, fps=fps, loop=loop,
                    start_paused=paused, **options,
                )  # fmt: skip
            if wait:
                opened.wait_ready(wait)
        except BaseException:
            opened.close()
            raise
        return opened

    def sessions(self) -> list[dict[str, Any]]:
        """The server's live sessions (name, clients, simulation, video streams)."""
        listed: list[dict[str, Any]] = self.rest.json("GET", "/api/sessions")
        return listed

    def health(self) -> dict[str, Any]:
        """The server's `/healthz`: its render device, image encoder and video encoders."""
        answer: dict[str, Any] = self.rest.json("GET", "/healthz")
        return answer

    def dashboard_url(self, session: str | Session | None = None) -> str:
        """The browser dashboard's link (with this client's token) for `session` (a name or
        a `Session`)."""
        name = session.name if isinstance(session, Session) else session
        query = [("session", name)] if name else []
        if self.token:
            query.append(("token", self.token))
        return f"{self.url}/" + (f"?{urlencode(query)}" if query else "")

    # ------------------------------------------------------------------ REST: renders, jobs

    def render(
        self,
        path: str | os.PathLike[str],
        width: int = 800,
        height: int = 600,
        *,
        params: Mapping[str, Any] | RenderParams | None = None,
        camera: Camera | Mapping[str, Any] | None = None,
        frame: int = 0,
        mode: str = "RGB",
    ) -> Any:
        """One picture of a structure file (PDB, mmCIF, GRO, ...) as a numpy array."""
        fields: dict[str, Any] = {"width": width, "height": height, "frame": frame}
        if params is not None:
            fields["params"] = checked_params(params)
        if camera is not None:
            fields["camera"] = checked_camera(camera)
        answer = self.rest.request("POST", "/api/render", form=fields, files={"file": path})
        return images.array(answer.content, mode)

    def submit_job(
        self,
        topology: str | os.PathLike[str],
        trajectory: str | os.PathLike[str] | Sequence[str | os.PathLike[str]] = (),
        *,
        output: Literal["zip", "mp4"] = "mp4",
        width: int = 640,
        height: int = 480,
        start: int = 0,
        stop: int | None = None,
        stride: int = 1,
        fps: float = 30.0,
        params: Mapping[str, Any] | RenderParams | None = None,
        camera: Camera | Mapping[str, Any] | None = None,
    ) -> Job:
        """Render a trajectory on the server (uploaded from here) to an MP4 or a zip of PNGs;
        `job.wait(progress=print)` follows it, `job.download(path)` fetches the result."""
        trajectories = (
            [trajectory] if isinstance(trajectory, str | os.PathLike) else list(trajectory)
        )
        fields: dict[str, Any] = {"output": output, "width": width, "height": height,
                                  "start": start, "stop": stop, "stride": stride,
                                  "fps": fps}  # fmt: skip
        if params is not None:
            fields["params"] = checked_params(params)
        if camera is not None:
            fields["camera"] = checked_camera(camera)
        files: dict[str, Any] = {"topology": topology}
        if trajectories:
            files["trajectory"] = trajectories
        info = self.rest.json("POST", "/api/jobs", form=fields, files=files, timeout=600)
        return Job(self.rest, info)

    def job(self, job_id: str) -> Job:
        return Job(self.rest, self.rest.json("GET", f"/api/jobs/{job_id}"))

    def recordings(self) -> list[Recording]:
        """The server's recordings, newest first."""
        return [Recording(self.rest, info) for info in self.rest.json("GET", "/api/recordings")]

    def recording(self, rec_id: str) -> Recording:
        return Recording(self.rest, self.rest.json("GET", f"/api/recordings/{rec_id}"))

    # ------------------------------------------------------------------ ending

    def forget(self, session: Session) -> None:
        """`session` has left: it is no longer listed."""
        if session in self._sessions:
            self._sessions.remove(session)

    def close(self) -> None:
        """Leave every session this client opened (the process's own server keeps running
        for other clients; it ends with the process, or with `scalesteer.shutdown()`)."""
        for session in list(self._sessions):
            session.close()
        self.rest.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        where = "its own server" if self.local is not None else self.url
        return f"Client({self.url}, {where}, {len(self._sessions)} sessions)"


def _close_local_clients() -> None:
    """Close the clients of the process's own server, and what feeds their sessions."""
    for client in list(_local_clients):
        with contextlib.suppress(Exception):
            client.close()


def shutdown() -> None:
    """Stop the server this process started (`connect()` without a URL), if any."""
    global _default_server
    _close_local_clients()
    with _default_lock:
        server, _default_server = _default_server, None
    if server is not None:
        server.stop()

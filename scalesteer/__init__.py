"""scalesteer from Python and Jupyter: steer a render server's sessions, take their pictures,
and watch them live in a notebook.

    import scalesteer, MDAnalysis as mda
    u = mda.Universe("system.gro", "run.xtc")
    scalesteer.show(u)          # a server of this process's own, the run replayed, a live view

`connect()` returns a `Client` (a server's URL and token, or one started here); `Client.open`
makes a session of an MDAnalysis Universe or AtomGroup, an MDTraj trajectory, ASE atoms or an
OpenMM simulation; a `Session` steers (`set(sigma_A=3)`), reads its state, renders pictures as
numpy arrays, records, films and subscribes; `Session.view()` is the notebook widget. Imports
neither warp-lang nor FastAPI: the server runs in a process of its own.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from protocol import ErrorCode
from scalesteer.callbacks import Subscription
from scalesteer.client import Client, shutdown
from scalesteer.errors import ScalesteerError, ServerStartError
from scalesteer.images import StreamedImage
from scalesteer.jobs import Job, JobFailedError, Recording
from scalesteer.session import Session
from scalesteer.state import SessionState

if TYPE_CHECKING:
    from scalesteer.widget import SessionView


def connect(url: str | None = None, token: str | None = None, **options: Any) -> Client:
    """A client of the server at `url` (a dashboard link with its token will do), or of a
    server of this process's own when `url` is None (see `Client`)."""
    return Client(url, token, **options)


def show(obj: Any, width: int = 640, height: int = 480, **options: Any) -> SessionView:
    """A live view of `obj` (a Universe, AtomGroup, MDTraj trajectory, ASE atoms or OpenMM
    simulation) in a session of this process's own server; `options` go to `Client.open`."""
    client = connect(**{k: options.pop(k) for k in ("url", "token", "device") if k in options})
    session = client.open(obj, **options)
    return session.view(width, height)


__all__ = [
    "Client",
    "ErrorCode",
    "Job",
    "JobFailedError",
    "Recording",
    "ScalesteerError",
    "ServerStartError",
    "Session",
    "SessionState",
    "SessionView",
    "StreamedImage",
    "Subscription",
    "connect",
    "show",
    "shutdown",
]


def __getattr__(name: str) -> Any:  # the widget loads anywidget only when asked for
    if name == "SessionView":
        from scalesteer.widget import SessionView

        return SessionView
    raise AttributeError(f"module 'scalesteer' has no attribute {name!r}")

"""The notebook widget: a session's live view in Jupyter (anywidget: JupyterLab, Notebook 7,
VS Code), its render parameters as traitlets.

The picture comes through the kernel: the widget's own link to the server (a viewer with its
own camera and size) receives each image on the client's background thread and forwards it to
the page as a custom message with the encoded bytes; the page draws it with the dashboard's
Viewport (JPEG, or H.264/AV1/VP9 video through WebCodecs where the browser decodes it) and
sends its views (orbit, pan, zoom) and picks back. The browser never needs to reach the
server, and the token never leaves the kernel. The link acknowledges each image once it is
handed to the kernel, so the server paces the stream to the kernel's link.

`sigma`, `iso`, `scale_space`, `mode` and `layers` follow the session: setting one steers
the session (checked by the protocol's models first: `view.sigma = -1` raises at once), and a
change made elsewhere (the dashboard, another widget, `Session.set`) shows up in them.
`camera` is this view's own camera (None: the session's); `picked` the last atom clicked.

The kernel sends the page a message at least once a second; when they stop (a restarted or
dead kernel) the view says so over its last picture. A restarted kernel ends its server too
(`LocalServer`), so running the cells again starts clean.
"""

from __future__ import annotations

import contextlib
import logging
import re
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, get_args

import anywidget
import traitlets
from pydantic import ValidationError

from protocol import Camera, Layer, Pick, RenderParams, SetRenderParams, VideoCodec, View
from protocol.fields import unknown_keys
from scalesteer import background
from scalesteer.errors import ScalesteerError
from scalesteer.link import ViewLink
from scalesteer.state import SessionState

if TYPE_CHECKING:
    from protocol import Image

log = logging.getLogger("scalesteer.widget")


class Viewed(Protocol):
    """What a widget needs of the session it shows (`scalesteer.session.Session`)."""

    @property
    def name(self) -> str: ...

    @property
    def link(self) -> ViewLink: ...

    @property
    def state(self) -> SessionState: ...

    @property
    def render_params(self) -> RenderParams: ...

    def set(self, **params: Any) -> RenderParams: ...

    def open_link(self, client: str) -> ViewLink: ...


HERE = Path(__file__).resolve().parent
CLIENT_SRC = HERE.parent / "client_web" / "src"
ENTRIES = ("camera.js", "video.js", "viewport.js", "video.worker.js")
"""The dashboard's modules the widget runs itself; the modules they import come with them."""
_IMPORT = re.compile(r"""(?:from|import)\s*["']\./([\w.-]+\.js)["']""")
HEARTBEAT_S = 1.0
CODECS = get_args(VideoCodec)
# trait -> the render parameter it shows
STEERED = {"sigma": "sigma_A", "iso": "iso_level", "scale_space": "scale_space", "mode": "mode"}


def dashboard_modules() -> list[list[str]]:
    """[name, source] of the dashboard modules the widget loads (client_web/src), each after
    the modules it imports: a module the dashboard's viewport comes to import comes along (the
    widget had shown no picture once the viewport imported cell.js and labels.js)."""
    ordered: dict[str, str] = {}

    def visit(name: str, path: tuple[str, ...]) -> None:
        if name in ordered:
            return
        if name in path:
            raise RuntimeError(f"client_web/src: an import cycle through {name}")
        source = (CLIENT_SRC / name).read_text()
        for dependency in _IMPORT.findall(source):
            visit(dependency, (*path, name))
        ordered[name] = source

    for entry in ENTRIES:
        visit(entry, ())
    return [[name, source] for name, source in ordered.items()]


class SessionView(anywidget.AnyWidget):
    """A live, steerable view of a `Session` (make it with `Session.view()`)."""

    _esm = HERE / "widget.js"
    _css = HERE / "widget.css"
    _modules: traitlets.List[list[str]] = traitlets.List().tag(sync=True)

    width = traitlets.Int(640).tag(sync=True)
    height = traitlets.Int(480).tag(sync=True)
    sigma = traitlets.Float(1.5).tag(sync=True)
    """The session's scale sigma in angstrom (`RenderParams.sigma_A`)."""
    iso = traitlets.Float(0.25).tag(sync=True)
    """The iso level (`RenderParams.iso_level`)."""
    scale_space = traitlets.Unicode("classical").tag(sync=True)
    """classical, geodesic or carved."""
    mode = traitlets.Unicode("iso").tag(sync=True)
    """iso (a surface) or volume (a cloud)."""
    layers = traitlets.List(traitlets.Dict()).tag(sync=True)
    """The session's layers as dicts (`protocol.Layer` fields); [] draws every atom alike."""
    camera = traitlets.Dict(allow_none=True, default_value=None).tag(sync=True)
    """This view's camera (`protocol.Camera` fields); None: the session's."""
    session_camera = traitlets.Dict(allow_none=True, default_value=None).tag(sync=True)
    video = traitlets.Bool(True).tag(sync=True)
    """Stream video where the browser decodes it (else JPEG images)."""
    picked = traitlets.Dict().tag(sync=True)
    """The last pick: atom, element, name, residue, position (`protocol.Picked` fields)."""
    session_name = traitlets.Unicode("").tag(sync=True)
    status = traitlets.Unicode("connecting").tag(sync=True)
    frames_shown = traitlets.Int(0).tag(sync=True)
    """Pictures the page has drawn (the page reports it every second)."""
    fps = traitlets.Float(0.0).tag(sync=True)
    """Pictures the page drew in its last second."""

    def __init__(self, session: Viewed, width: int = 640, height: int = 480, **kwargs: Any):
        state = session.state
        super().__init__(
            _modules=dashboard_modules(),
            width=width,
            height=height,
            session_name=session.name,
            **self._traits_of(state),
            **kwargs,
        )
        self.session = session
        self.images_sent = 0
        self._guard = threading.local()
        self._closed = False
        self.link: ViewLink = session.open_link("scalesteer-widget")
        self.link.on_image.append(self._forward)
        self.link.on_close.append(self._link_closed)
        session.link.on_state.append(self._session_state)
        self.on_msg(self._page_message)
        self.status = "connected"
        self._send_view(View(width=width, height=height, camera=self._own_camera()))
        background.call_soon(self._heartbeat)

    # ------------------------------------------------------------------ session -> traits

    @staticmethod
    def _traits_of(state: SessionState) -> dict[str, Any]:
        params = state.render_params
        traits: dict[str, Any] = {trait: getattr(params, field) for trait, field in STEERED.items()}
        traits["layers"] = [lay.model_dump(mode="json", exclude_none=True) for lay in params.layers]
        traits["session_camera"] = (
            None if state.camera is None else state.camera.model_dump(mode="json")
        )
        return traits

    def _session_state(self, state: SessionState) -> None:  # the client's loop
        traits = self._traits_of(state)
        self._guard.quiet = True  # these came from the server: not steered back
        try:
            for name, value in traits.items():
                if getattr(self, name) != value:
                    setattr(self, name, value)
        finally:
            self._guard.quiet = False

    # ------------------------------------------------------------------ traits -> session

    @traitlets.validate("sigma", "iso", "scale_space", "mode", "layers")
    def _check(self, proposal: dict[str, Any]) -> Any:
        name, value = proposal["trait"].name, proposal["value"]
        key = STEERED.get(name, name)
        unknown = unknown_keys(RenderParams, {key: value}, "render_params.params")
        if unknown is not None:  # a layer with a key no layer has
            raise traitlets.TraitError(f"{name}: {unknown}: unknown field")
        try:
            SetRenderParams(params={key: value})
        except ValidationError as exc:
            err = exc.errors(include_url=False)[0]
            raise traitlets.TraitError(f"{name}: {err['msg']} (render_params.{key})") from None
        return value

    @traitlets.observe("sigma", "iso", "scale_space", "mode", "layers")
    def _steer(self, change: dict[str, Any]) -> None:
        if not hasattr(self, "session") or getattr(self._guard, "quiet", False):
            return
        name = change["name"]
        key = STEERED.get(name, name)
        value = change["new"]
        if name == "layers":
            value = [Layer.model_validate(lay).model_dump(exclude_none=True) for lay in value]
        try:
            self.session.set(**{key: value})
        except ScalesteerError:
            # the session did not take it: the trait shows what the session has, then raise
            self._session_state(self.session.state)
            raise

    @traitlets.observe("camera")
    def _camera_changed(self, change: dict[str, Any]) -> None:
        if not hasattr(self, "link") or getattr(self._guard, "quiet", False):
            return
        self._send_view(View(width=self.width, height=self.height, camera=self._own_camera()))

    @traitlets.validate("camera")
    def _check_camera(self, proposal: dict[str, Any]) -> Any:
        value = proposal["value"]
        if value is None:
            return None
        try:
            return Camera.model_validate(value).model_dump(mode="json")
        except ValidationError as exc:
            err = exc.errors(include_url=False)[0]
            raise traitlets.TraitError(f"camera: {err['msg']}") from None

    def _own_camera(self) -> Camera | None:
        return None if self.camera is None else Camera.model_validate(self.camera)

    # ------------------------------------------------------------------ page <-> server

    def _page_message(self, _widget: Any, content: dict[str, Any], _buffers: Any) -> None:
        kind = content.get("type")
        try:
            if kind == "view":
                view = View(
                    camera=content.get("camera"),
                    width=max(1, int(content.get("width") or self.width)),
                    height=max(1, int(content.get("height") or self.height)),
                    interacting=bool(content.get("interacting")),
                    video=[c for c in content.get("video") or [] if c in CODECS],
                )
                if view.camera is not None:
                    self._guard.quiet = True
                    try:
                        self.camera = view.camera.model_dump(mode="json")
                    finally:
                        self._guard.quiet = False
                self._send_view(view)
            elif kind == "pick":
                pick = Pick(x=int(content["x"]), y=int(content["y"]))
                background.submit(self._pick(pick))
            elif kind == "shown":
                self.frames_shown = int(content.get("frames") or 0)
                self.fps = float(content.get("fps") or 0.0)
        except (ValidationError, ValueError, KeyError, TypeError) as exc:
            log.warning("scalesteer widget: ignoring a malformed %s from the page: %s", kind, exc)

    def _send_view(self, view: View) -> None:
        if self.link.closed is None:
            background.submit(self.link.view(view, self.link.reserve_view()))

    async def _pick(self, pick: Pick) -> None:
        try:
            picked = await self.link.request(pick, 10.0)
        except (ScalesteerError, TimeoutError) as exc:
            log.warning("scalesteer widget: pick failed: %s", exc)
            return
        content = picked.model_dump(mode="json", exclude={"seq", "ref"})
        self.picked = content
        self.send({**content, "type": "picked"})

    def _forward(self, image: Image) -> None:  # the client's loop: hand it over, acknowledge
        meta = image.model_dump(mode="json", exclude={"data", "histogram", "seq"})
        try:
            self.send(meta, [image.data])
        except Exception:  # the kernel's comm is gone (closing): stop forwarding
            return
        self.images_sent += 1
        background.submit(self.link.ack(image.frame_id))

    def _heartbeat(self) -> None:  # the client's loop, every second while the widget lives
        if self._closed:
            return
        closed = self.link.closed
        with contextlib.suppress(Exception):
            self.send(
                {
                    "type": "status",
                    "status": "connected" if closed is None else "closed",
                    "message": "" if closed is None else f"The link to the server is {closed}.",
                    "time": time.time(),
                }
            )
        background.loop().call_later(HEARTBEAT_S, self._heartbeat)

    def _link_closed(self, reason: str) -> None:
        self.status = f"closed: {reason}"

    # ------------------------------------------------------------------ reading

    @property
    def render_params(self) -> RenderParams:
        return self.session.render_params

    def close(self) -> None:
        """Close the view and its link (the session stays open)."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(ValueError):
            self.session.link.on_state.remove(self._session_state)
        if not background.in_loop():
            with contextlib.suppress(Exception):
                background.run(self.link.close(), 10)
        super().close()

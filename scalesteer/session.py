"""A session from Python: steer it, read its state, take its pictures, subscribe to it.

Every steering call is checked by the protocol's models before it is sent (a value out of
range raises at once, naming the field) and then waits for the server's answer: the `state`
that names it for render parameters, the simulation's acknowledgement for simulation
parameters and run control. A refusal raises `ScalesteerError` with the server's code and path.

Kept whole: `Session` is the Python client's public surface, one method per steering call or
query, and splitting the class would split the API docs/python.md describes."""

from __future__ import annotations

import numbers
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Literal, Protocol

import numpy as np
import numpy.typing as npt
from pydantic import ValidationError

from protocol import (
    Camera,
    Control,
    ErrorCode,
    Event,
    Image,
    Layer,
    ParamsAck,
    Pull,
    RenderParams,
    Role,
    Select,
    Selected,
    SetRenderParams,
    SimParams,
    SimStatus,
    View,
)
from protocol.fields import error_location, unknown_keys
from scalesteer import background, images
from scalesteer.callbacks import Subscription
from scalesteer.errors import ScalesteerError
from scalesteer.images import StreamedImage
from scalesteer.jobs import Job, Recording
from scalesteer.link import ViewLink
from scalesteer.rest import Rest
from scalesteer.state import SessionState

if TYPE_CHECKING:
    from scalesteer.widget import SessionView


class Owner(Protocol):
    """What a session needs of the client that opened it (`scalesteer.client.Client`)."""

    url: str
    rest: Rest
    role: Role

    def open_link(self, name: str, role: Role, client: str) -> ViewLink:
        """A link of its own to session `name`."""

    def forget(self, session: Session) -> None:
        """The session has left: the client stops listing it."""


TIMEOUT_S = 30.0
IDLE_VIEW = View(width=1, height=1)
"""The control link's view while nobody subscribed to its images: the server renders every
viewer, and a 1x1 render of the frame the other views draw costs next to nothing."""


def invalid(exc: ValidationError, prefix: str) -> ScalesteerError:
    """A pydantic refusal as the error the server would have sent (code, dotted path)."""
    loc, msg = error_location(exc.errors(include_url=False)[0])
    path = ".".join([prefix, *loc]) if loc else prefix
    return ScalesteerError(ErrorCode.INVALID_MESSAGE, f"{path}: {msg}", path)


def checked_params(
    params: Mapping[str, Any] | RenderParams,
    prefix: str = "params",
    base: RenderParams | None = None,
) -> dict[str, Any]:
    """Render parameters for a REST form, checked here as the server checks them: a key no
    field has is refused by name (the model alone drops it in silence, and `sigmaa` would
    render the default). Only what `params` names is sent, so the server's own choices hold
    where they are not named (layers: a file opens on its molecule, solvent hidden). With
    `base` (a session's parameters), `params` are changes to it, and its layers stay the
    session's unless `params` name them. A `RenderParams` names the fields it was given."""
    if isinstance(params, RenderParams):
        params = params.model_dump(exclude_unset=True)
    if not isinstance(params, Mapping):
        raise ScalesteerError(
            ErrorCode.INVALID_MESSAGE,
            f"{prefix}: a mapping of render parameters or RenderParams, not "
            f"{type(params).__name__}",
            prefix,
        )
    unknown = unknown_keys(RenderParams, dict(params), prefix)
    if unknown is not None:
        raise ScalesteerError(ErrorCode.INVALID_MESSAGE, f"{unknown}: unknown field", unknown)
    merged = dict(params)
    if base is not None:
        merged = {**base.model_dump(exclude={"layers"}), **merged}
    try:
        checked = RenderParams.model_validate(merged)
    except ValidationError as exc:
        raise invalid(exc, prefix) from None
    out: dict[str, Any] = checked.model_dump(mode="json", exclude_unset=True)
    return out


MAX_SIDE_ASKED = 2**31 - 1
"""The largest side a size may name (the server shrinks any past its own limits): 2**64 and
more cannot be sent at all, and such a view had gone out of the client's loop unsent."""


def checked_size(width: Any, height: Any, prefix: str) -> tuple[int, int]:
    """An image's size checked as the protocol checks it, before anything is sent or kept:
    whole numbers of pixels, at least 1 (`next_image(0, 0)` had left its view on the session,
    and every later subscription failed with it). Sizes past the server's limits are its to
    shrink."""
    for name, value in (("width", width), ("height", height)):
        whole = isinstance(value, numbers.Integral) and not isinstance(value, bool)
        if not whole or not 1 <= value <= MAX_SIDE_ASKED:
            path = f"{prefix}.{name}"
            raise ScalesteerError(
                ErrorCode.INVALID_MESSAGE,
                f"{path}: a whole number of pixels from 1 to {MAX_SIDE_ASKED}, not {value!r}",
                path,
            )
    return int(width), int(height)


def checked_camera(camera: Camera | Mapping[str, Any], prefix: str = "camera") -> dict[str, Any]:
    """A camera for a REST form, checked as the server checks it (unknown keys by name)."""
    if not isinstance(camera, Camera | Mapping):
        raise ScalesteerError(
            ErrorCode.INVALID_MESSAGE,
            f"{prefix}: a Camera or a mapping of its fields, not {type(camera).__name__}",
            prefix,
        )
    if not isinstance(camera, Camera):
        unknown = unknown_keys(Camera, dict(camera), prefix)
        if unknown is not None:
            raise ScalesteerError(ErrorCode.INVALID_MESSAGE, f"{unknown}: unknown field", unknown)
        try:
            camera = Camera.model_validate(dict(camera))
        except ValidationError as exc:
            raise invalid(exc, prefix) from None
    out: dict[str, Any] = camera.model_dump(mode="json")
    return out


class Source(Protocol):
    """What feeds a session from this process (a replayed trajectory, an OpenMM reporter);
    closed with the session."""

    def close(self) -> None: ...


class Session:
    """One session of a server, joined as a steerer (see `Client.session`)."""

    def __init__(self, client: Owner, link: ViewLink, timeout: float = TIMEOUT_S) -> None:
        self.client = client
        self.link = link
        self.timeout = timeout
        self.source: Source | None = None
        """What this process feeds the session with (`Client.open`), if anything."""
        self._lock = threading.Lock()
        self._images: list[tuple[Subscription, tuple[int, int]]] = []
        self._observers: list[Subscription] = []
        self._states: list[Subscription] = []
        self._events: list[Subscription] = []
        self._views: list[SessionView] = []
        link.on_image.append(self._image)
        link.on_state.append(self._state)
        link.on_event.append(self._event)
        self._status: SimStatus | None = None

    # ------------------------------------------------------------------ reading

    @property
    def name(self) -> str:
        return self.link.session_id

    @property
    def state(self) -> SessionState:
        """The session's state as the server last described it."""
        return self.link.state

    @property
    def render_params(self) -> RenderParams:
        return self.link.state.render_params

    def open_link(self, client: str) -> ViewLink:
        """Another link to this session, with this session's role (a widget's own)."""
        return self.client.open_link(self.name, self.client.role, client)

    @property
    def layers(self) -> list[Layer]:
        return list(self.link.state.render_params.layers)

    @property
    def camera(self) -> Camera | None:
        """The session's camera (the server frames the molecule with it)."""
        return self.link.state.camera

    @property
    def sim(self) -> SimStatus:
        """The simulation's status: state, step, time, atoms, observables."""
        return self.link.state.sim

    @property
    def observables(self) -> dict[str, float]:
        """The latest named scalars of the simulation (`temperature_K`, ...)."""
        return dict(self.link.state.sim.observables)

    def wait_for(
        self, predicate: Callable[[SessionState], bool], timeout: float = 60.0
    ) -> SessionState:
        """Wait until the session's state satisfies `predicate`; `TimeoutError` otherwise."""
        done = threading.Event()

        def check(state: SessionState) -> None:
            if predicate(state):
                done.set()

        self.link.on_state.append(check)
        try:
            check(self.link.state)
            if not done.wait(timeout):
                raise TimeoutError(f"the session's state did not get there within {timeout} s")
        finally:
            self.link.on_state.remove(check)
        return self.link.state

    def wait_ready(self, timeout: float = 60.0) -> SessionState:
        """Wait until a simulation has sent the session a topology and a frame (the server
        frames the molecule with the session's camera at the first frame)."""
        return self.wait_for(lambda s: s.sim.n_atoms > 0 and s.camera is not None, timeout)

    # ------------------------------------------------------------------ steering the picture

    def set(self, **params: Any) -> RenderParams:
        """Change render parameters (`sigma_A=3`, `iso_level=0.3`, `scale_space="geodesic"`,
        `lighting={"ambient": 0.4}`, `layers=[...]`, ...): only what is named changes. Returns
        the session's parameters with the change."""
        unknown = unknown_keys(RenderParams, params, "render_params.params")
        if unknown is not None:
            raise ScalesteerError(ErrorCode.INVALID_MESSAGE, f"{unknown}: unknown field", unknown)
        try:
            message = SetRenderParams(params=params)
        except ValidationError as exc:
            raise invalid(exc, "render_params") from None
        self._request(message)
        return self.render_params

    def set_layers(self, layers: Sequence[Layer | Mapping[str, Any]]) -> list[Layer]:
        """Replace the session's layers (an empty list draws every atom alike)."""
        if isinstance(layers, str | bytes | Mapping | Layer):
            raise TypeError(
                "set_layers takes a list of layers, e.g. [{'selection': 'protein'}], not "
                f"{type(layers).__name__}"
            )
        plain = [lay.model_dump(exclude_none=True) if isinstance(lay, Layer) else dict(lay)
                 for lay in layers]  # fmt: skip
        self.set(layers=plain)
        return self.layers

    def select(self, text: str) -> Selected:
        """Count the atoms a selection picks now (nothing changes); `error` and `position` say
        what is wrong with a bad one."""
        try:
            message = Select(text=text)
        except ValidationError as exc:
            raise invalid(exc, "select") from None
        answer: Selected = self._request(message)
        return answer

    # ------------------------------------------------------------------ steering the simulation

    def set_sim(self, **params: Any) -> ParamsAck:
        """Change simulation parameters (`temperature_K`, `timestep_fs`, `friction_per_ps`,
        `frame_interval`, `engine={...}`); returns the acknowledgement with the step at which
        the simulation applied them."""
        try:
            message = SimParams(**params)
        except ValidationError as exc:
            raise invalid(exc, "sim_params") from None
        ack: ParamsAck = self._request(message)
        return ack

    def control(self, action: str, **fields: Any) -> ParamsAck:
        """Run control: `pause`, `resume`, `reset`, `step` (n_steps), `seek` (frame), `speed`
        (speed), `loop` (loop), `stop`."""
        try:
            message = Control(action=action, **fields)
        except ValidationError as exc:
            raise invalid(exc, "control") from None
        ack: ParamsAck = self._request(message)
        return ack

    def pause(self) -> ParamsAck:
        return self.control("pause")

    def resume(self) -> ParamsAck:
        return self.control("resume")

    def pull(
        self,
        atom: int,
        target: Sequence[float] | None = None,
        *,
        force: Sequence[float] | None = None,
        spring_k: float = 10.0,
        max_force: float = 1000.0,
    ) -> None:
        """Pull `atom` with a spring toward `target` (angstrom), or push it with a constant
        `force` (kJ/mol/A); the server caps it at the engine's limits. `release` ends it."""
        try:
            message = Pull(
                atom=atom,
                target=None if target is None else tuple(target),
                force=None if force is None else tuple(force),
                spring_k=spring_k,
                max_force=max_force,
            )
        except ValidationError as exc:
            raise invalid(exc, "pull") from None
        self._request(message)

    def release(self, atom: int) -> None:
        """Stop pulling `atom`."""
        self._request(Pull(atom=atom, release=True))

    def _request(self, message: Any) -> Any:
        return background.run(self.link.request(message, self.timeout), self.timeout + 5)

    # ------------------------------------------------------------------ pictures

    def image_bytes(
        self,
        width: int = 640,
        height: int = 480,
        *,
        camera: Camera | Mapping[str, Any] | None = None,
        params: Mapping[str, Any] | RenderParams | None = None,
        format: Literal["png", "jpeg"] = "png",
    ) -> bytes:
        """The session's latest frame rendered now at full quality (REST `/api/render`), with
        the session's render parameters and camera unless `params` (changes to them) or
        `camera` are given."""
        width, height = checked_size(width, height, "render")
        fields: dict[str, Any] = {"session": self.name, "width": width, "height": height,
                                  "format": format}  # fmt: skip
        if params:
            fields["params"] = checked_params(params, base=self.render_params)
        if camera is not None:
            fields["camera"] = checked_camera(camera)
        return self.client.rest.request("POST", "/api/render", form=fields).content

    def image(
        self, width: int = 640, height: int = 480, *, mode: str = "RGB", **kw: Any
    ) -> npt.NDArray[np.uint8]:
        """The session's current picture as a (height, width, 3) uint8 array (see
        `image_bytes` for the options)."""
        return images.array(self.image_bytes(width, height, **kw), mode)

    def pil_image(
        self, width: int = 640, height: int = 480, *, mode: str = "RGB", **kw: Any
    ) -> Any:
        """The session's current picture as a PIL image."""
        return images.decode(self.image_bytes(width, height, **kw), mode)

    # ------------------------------------------------------------------ subscriptions

    def on_image(
        self, callback: Callable[[StreamedImage], None], width: int = 640, height: int = 480
    ) -> Subscription:
        """Call `callback(image)` with every image of the live stream at this size (JPEG;
        newest first: a slow callback skips images instead of queueing them). The images
        come from the session's camera; on a CPU device the server shrinks live images to
        what it renders within its frame budget (`image.size` says what came), a still at
        full size follows when nothing changes. `close()` the subscription to stop them."""
        size = checked_size(width, height, "view")
        sub = self._subscription(callback)
        with self._lock:
            self._images.append((sub, size))
        self._update_view()
        return sub

    def next_image(
        self, width: int = 640, height: int = 480, timeout: float = 60.0
    ) -> StreamedImage:
        """Wait for the next image of the live stream at this size (as `on_image`), at most
        `timeout` seconds; a link that ends meanwhile raises at once (`not_ready`)."""
        got: list[StreamedImage] = []
        arrived = threading.Event()

        def take(image: StreamedImage) -> None:
            got.append(image)
            arrived.set()

        def ended(_reason: str) -> None:
            arrived.set()

        self.link.on_close.append(ended)
        try:
            if self.link.closed is None:
                with self.on_image(take, width, height):
                    arrived.wait(timeout)
        finally:
            self.link.on_close.remove(ended)
        if got:
            return got[0]
        if self.link.closed is not None:
            self.link.check_open()
        raise TimeoutError(f"no image within {timeout} s")

    def on_observables(self, callback: Callable[[SimStatus], None]) -> Subscription:
        """Call `callback(status)` whenever the simulation reports (step, time, observables
        such as `temperature_K`; the server sends them about ten times a second)."""
        sub = self._subscription(callback)
        with self._lock:
            self._observers.append(sub)
        return sub

    def on_state(self, callback: Callable[[SessionState], None]) -> Subscription:
        """Call `callback(state)` whenever the session's state changes."""
        sub = self._subscription(callback)
        with self._lock:
            self._states.append(sub)
        return sub

    def on_event(self, callback: Callable[[Event], None]) -> Subscription:
        """Call `callback(event)` for the session's events (a guard that rolled a run back,
        a recording that skips frames, ...)."""
        sub = self._subscription(callback)
        with self._lock:
            self._events.append(sub)
        return sub

    def _subscription(self, callback: Callable[[Any], None]) -> Subscription:
        """A subscription of `callback`; `not_ready` once the link has ended (it would never
        be called)."""
        if self.link.closed is not None:
            self.link.check_open()
        return Subscription(callback, self._unsubscribe)

    def _unsubscribe(self, sub: Subscription) -> None:
        with self._lock:
            self._images = [(s, size) for s, size in self._images if s is not sub]
            for group in (self._observers, self._states, self._events):
                if sub in group:
                    group.remove(sub)
        self._update_view()

    def _update_view(self) -> None:
        with self._lock:
            sizes = [size for _, size in self._images]
        view = IDLE_VIEW if not sizes else View(width=max(w for w, _ in sizes),
                                                height=max(h for _, h in sizes))  # fmt: skip
        if self.link.closed is None:
            # the seq is taken here, before the caller goes on: an image of the idle view
            # already on its way cannot reach a callback subscribed just now
            background.submit(self.link.view(view, self.link.reserve_view()))

    def _image(self, message: Image) -> None:  # the client's loop
        # images rendered for the view before the last one (the idle 1x1) are not wanted
        if message.format not in ("jpeg", "png") or (message.ref or 0) < self.link.view_seq:
            return
        with self._lock:
            subs = [s for s, _ in self._images]
        for sub in subs:
            sub.offer(StreamedImage(message))

    def _state(self, state: SessionState) -> None:  # the client's loop
        with self._lock:
            states, observers = list(self._states), list(self._observers)
        for sub in states:
            sub.offer(state)
        if state.sim is not self._status:
            self._status = state.sim
            for sub in observers:
                sub.offer(state.sim)

    def _event(self, event: Event) -> None:  # the client's loop
        with self._lock:
            subs = list(self._events)
        for sub in subs:
            sub.offer(event)

    # ------------------------------------------------------------------ recordings, movies, log

    def record(self, stride: int = 1, max_bytes: int | None = None) -> Recording:
        """Start recording the run (frames, topology, steering) until `stop()`."""
        body: dict[str, Any] = {"stride": stride}
        if max_bytes is not None:
            body["max_bytes"] = max_bytes
        info = self.client.rest.json(
            "POST", f"/api/sessions/{self.name}/recordings", json_body=body
        )
        return Recording(self.client.rest, info)

    def movie(
        self,
        width: int = 640,
        height: int = 480,
        fps: float = 30.0,
        max_frames: int | None = None,
        camera: Camera | Mapping[str, Any] | None = None,
    ) -> Job:
        """Film the live session to an MP4 (a job: `cancel()` ends it and keeps the movie)."""
        fields: dict[str, Any] = {"width": width, "height": height, "fps": fps,
                                  "max_frames": max_frames}  # fmt: skip
        if camera is not None:
            fields["camera"] = checked_camera(camera)
        info = self.client.rest.json("POST", f"/api/sessions/{self.name}/movies", form=fields)
        return Job(self.client.rest, info)

    def log(self) -> list[dict[str, Any]]:
        """The session's steering log: every accepted action, with the step it applied at."""
        entries: list[dict[str, Any]] = self.client.rest.json(
            "GET", f"/api/sessions/{self.name}/log"
        )
        return entries

    # ------------------------------------------------------------------ the notebook widget

    def view(self, width: int = 640, height: int = 480, **traits: Any) -> SessionView:
        """A live view of this session for Jupyter (anywidget; `pip install
        scalesteer[notebook]`): drag to orbit, right-drag to pan, wheel to zoom, click to
        pick; `view.sigma = 3` steers the session."""
        from scalesteer.widget import SessionView

        view = SessionView(self, width=width, height=height, **traits)
        self._views.append(view)
        return view

    # ------------------------------------------------------------------ ending

    def close(self) -> None:
        """Leave the session: close its views, subscriptions, links and what feeds it."""
        for view in list(self._views):
            view.close()
        self._views.clear()
        with self._lock:
            subs = [s for s, _ in self._images] + self._observers + self._states + self._events
        for sub in subs:
            sub.close()
        if self.source is not None:
            self.source.close()
            self.source = None
        if not background.in_loop():
            background.run(self.link.close(), 10)
        self.client.forget(self)

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        sim = self.sim
        return (
            f"Session({self.name!r}, {sim.state}, {sim.n_atoms} atoms, step {sim.step}, "
            f"on {self.client.url})"
        )

"""Every message of every connection, as pydantic models in one union tagged by `type`.

Directions: S = simulation adapter, V = viewer/steerer (browser or script), * = server.
Units: angstrom, ps, K, kJ/mol, kJ/mol/A. Optional fields default to None and are omitted
on the wire, which is what lets old peers ignore what new peers add.

Kept whole: the wire schema in one place, so the JSON Schema (`protocol.schema`), docs/protocol.md
and the test vectors are generated from one file and its one tagged union.
"""

from __future__ import annotations

import types
import typing
from typing import TYPE_CHECKING, Annotated, Any, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, create_model, model_validator
from pydantic_core import PydanticCustomError

from protocol.arrays import AtomFloats, AtomInts, Bonds, Box, Floats, Positions
from protocol.errors import ErrorCode
from protocol.limits import MAX_CAMERA_A, Limits

PROTOCOL_VERSION = "1.9"
"""major.minor: a major change breaks old peers; a minor one only adds defaulted fields."""

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
CameraLength = Annotated[float, Field(gt=0, le=MAX_CAMERA_A, allow_inf_nan=False)]
"""A camera's distance or view height in angstrom (`MAX_CAMERA_A`)."""
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Unit = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]
Coordinate = Annotated[float, Field(ge=-1e6, le=1e6, allow_inf_nan=False)]
"""A position in angstrom; a million angstrom (0.1 mm) is beyond any simulation box."""
Point = tuple[Coordinate, Coordinate, Coordinate]
RGB = tuple[Unit, Unit, Unit]
Seq = Annotated[int, Field(ge=0, lt=2**53)]
Name = Annotated[str, Field(max_length=64)]

Role = Literal["simulation", "steerer", "viewer"]
VideoCodec = Literal["h264", "h264-baseline", "av1", "vp9"]
"""Video codecs a viewer may decode: H.264 High and Constrained Baseline, AV1, VP9 profile 0."""
ImageFormat = Literal["jpeg", "png", "h264", "av1", "vp9"]
SESSION_NAME = r"^[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}$"
"""Session names: letters, digits, '_', '-', '.', not starting with '.' (they name log files)."""


def _is_number(annotation: Any) -> bool:
    """Whether a field's type is a number (int or float, optionally None), not a bool."""
    if typing.get_origin(annotation) is Annotated:
        return _is_number(typing.get_args(annotation)[0])
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        kinds = [a for a in typing.get_args(annotation) if a is not type(None)]
        return bool(kinds) and all(_is_number(a) for a in kinds)
    return annotation in (int, float)


_NUMBER_FIELDS: dict[tuple[type, str], bool] = {}
"""Which (model, field) pairs hold a number, learnt on first use."""


def _number_field(model: type[BaseModel], name: Any) -> bool:
    """Whether `name` is a number field of `model`. Only the model's own fields are learnt: a
    key a client makes up is no field, and must not grow the table."""
    field = model.model_fields.get(str(name))
    if field is None:
        return False
    key = (model, str(name))
    number = _NUMBER_FIELDS.get(key)
    if number is None:
        number = _NUMBER_FIELDS[key] = _is_number(field.annotation)
    return number


class Model(BaseModel):
    """Base of every wire model: unknown fields are ignored (forward compatibility)."""

    model_config = ConfigDict(extra="ignore", frozen=True, use_enum_values=True)

    @model_validator(mode="before")
    @classmethod
    def _no_booleans_for_numbers(cls, data: Any) -> Any:
        """true or false where a number goes is refused: pydantic would read it as 1 or 0
        (`sigma_A: true` drew at 1 A), where a client had meant something else."""
        if isinstance(data, dict):
            for name, value in data.items():
                if isinstance(value, bool) and _number_field(cls, name):
                    raise PydanticCustomError(
                        "bool_for_number",
                        "{field}: true or false is not a number",
                        {"field": str(name)},
                    )
        return data


class Message(Model):
    """Base of every top-level message: optional `seq`, echoed by replies as `ref`."""

    type: str
    seq: Seq | None = None


# ---------------------------------------------------------------- handshake (any -> *, * -> any)


class Hello(Message):
    """First message on every connection."""

    type: Literal["hello"] = "hello"
    role: Role
    protocol_version: str = PROTOCOL_VERSION
    token: Annotated[str, Field(max_length=256)] | None = None
    client: Annotated[str, Field(max_length=128)] = "unknown"
    session: Annotated[str, Field(pattern=SESSION_NAME)] | None = None
    instance: Annotated[str, Field(max_length=64)] | None = None
    """The client's identity across its reconnections. A simulation's (random per adapter
    process): a new connection of the same instance replaces the old one; another instance is
    refused while the session has a simulation, unless it asks to `takeover`. A dashboard
    page's (random per browser tab): recordings and movies it starts naming it as their
    `owner` end once no connection of it has been in the session for the server's
    `owner_grace_s`."""
    takeover: bool = False


class Welcome(Message):
    """The server's answer to `hello`: what was granted and the limits that apply."""

    type: Literal["welcome"] = "welcome"
    session_id: str
    client_id: str
    role: Role
    protocol_version: str = PROTOCOL_VERSION
    server: str = "scalesteer"
    limits: Limits = Limits()


# ---------------------------------------------------------------- simulation -> server


class Topology(Message):
    """S->*: who the atoms are; sent once per connection, before frames."""

    type: Literal["topology"] = "topology"
    n_atoms: Annotated[int, Field(ge=0)]
    elements: list[Annotated[str, Field(max_length=3)]]
    names: list[Annotated[str, Field(max_length=8)]]
    residue_ids: AtomInts
    residue_names: list[Annotated[str, Field(max_length=8)]]
    chain_ids: list[Annotated[str, Field(max_length=4)]]
    bonds: Bonds
    radii: AtomFloats | None = None
    charges: AtomFloats | None = None
    bfactors: AtomFloats | None = None
    title: Annotated[str, Field(max_length=256)] = ""
    engine: Annotated[str, Field(max_length=64)] = ""

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        n = self.n_atoms
        for name in ("elements", "names", "residue_names", "chain_ids"):
            got = len(getattr(self, name))
            if got != n:
                raise ValueError(f"{name} has {got} entries, n_atoms is {n}")
        for name in ("residue_ids", "radii", "charges", "bfactors"):
            arr = getattr(self, name)
            if arr is not None and arr.shape[0] != n:
                raise ValueError(f"{name} has {arr.shape[0]} entries, n_atoms is {n}")
        if self.bonds.count:
            b = self.bonds.to_numpy()
            if int(b.min()) < 0 or int(b.max()) >= n:
                raise ValueError(f"bond index out of range [0, {n})")
        return self


class Frame(Message):
    """S->*: one configuration. `observables` holds named scalars (temperature_K, ...)."""

    type: Literal["frame"] = "frame"
    step: Annotated[int, Field(ge=0)]
    time_ps: FiniteFloat
    positions: Positions
    box: Box | None = None
    velocities: Positions | None = None
    observables: dict[Name, FiniteFloat] = Field(default_factory=dict, max_length=64)

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        if self.box is not None and self.box.shape != (3, 3):
            raise ValueError(f"box must be (3, 3), got {list(self.box.shape)}")
        if self.velocities is not None and self.velocities.shape != self.positions.shape:
            raise ValueError("velocities and positions differ in shape")
        return self


class ParamsAck(Message):
    """S->* and *->V: a steering message (`ref` = its seq) took effect at `step`, or failed."""

    type: Literal["params_ack"] = "params_ack"
    ref: Seq
    ok: bool = True
    step: Annotated[int, Field(ge=0)] | None = None
    time_ps: FiniteFloat | None = None
    detail: Annotated[str, Field(max_length=1024)] = ""
    applied: dict[Name, Any] = Field(default_factory=dict, max_length=64)


# ---------------------------------------------------------------- engine (S -> *, * -> V)

ControlAction = Literal["pause", "resume", "reset", "step", "seek", "speed", "loop", "stop"]


class ParamRange(Model):
    """The values an engine accepts for one simulation parameter."""

    min: FiniteFloat
    max: FiniteFloat
    unit: Annotated[str, Field(max_length=16)] = ""
    recommended: FiniteFloat | None = None


class PullLimits(Model):
    """The most an engine lets a user pull with: per-atom force (kJ/mol/A) and spring
    constant (kJ/mol/A^2)."""

    max_force: PositiveFloat
    max_spring_k: PositiveFloat


class Playback(Model):
    """A replay's playback as it is now: its speed (times the rate it was opened at) and
    whether it starts again at its end."""

    speed: Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)] = 1.0
    loop: bool = False


class EngineInfo(Message):
    """S->*, and *->V in `state.engine`: what this simulation can be steered with.

    The server refuses steering outside it (naming the limit), and the dashboard disables what
    the engine cannot do, saying why (`unavailable`)."""

    type: Literal["engine"] = "engine"
    name: Annotated[str, Field(max_length=128)]
    kind: Literal["md", "replay", "imd"] = "md"
    controls: list[ControlAction] = Field(default_factory=list, max_length=16)
    params: dict[Name, ParamRange] = Field(default_factory=dict, max_length=32)
    unavailable: dict[Name, Annotated[str, Field(max_length=256)]] = Field(
        default_factory=dict, max_length=32
    )
    """Parameter or action -> why this engine cannot change it."""
    pull: PullLimits | None = None
    """None: this engine takes no external forces."""
    n_frames: Annotated[int, Field(ge=0)] | None = None
    """A replay's trajectory length."""
    guard: Annotated[str, Field(max_length=256)] = ""
    """What the adapter does when the simulation blows up, in a sentence."""
    playback: Playback | None = None
    """A replay's speed and loop as it starts; the server keeps them current as its `speed`
    and `loop` controls are acknowledged, so a viewer who joins later sees them as they are."""


class Event(Message):
    """S->* and *->V: something every user of the session should know about (the adapter's
    guard rolled back a blown-up run, a replay reached its end, ...)."""

    type: Literal["event"] = "event"
    level: Literal["info", "warning", "error"] = "info"
    code: Name
    message: Annotated[str, Field(max_length=1024)]
    step: Annotated[int, Field(ge=0)] | None = None


# ---------------------------------------------------------------- steering (V -> *, * -> S)

EngineParam = bool | int | FiniteFloat | Annotated[str, Field(max_length=256)]


class SimParams(Message):
    """V->* and *->S: change simulation parameters; only the fields present change."""

    type: Literal["sim_params"] = "sim_params"
    temperature_K: Annotated[float, Field(gt=0, le=10_000, allow_inf_nan=False)] | None = None
    timestep_fs: Annotated[float, Field(gt=0, le=20, allow_inf_nan=False)] | None = None
    friction_per_ps: Annotated[float, Field(ge=0, le=1000, allow_inf_nan=False)] | None = None
    frame_interval: Annotated[int, Field(ge=1, le=1_000_000)] | None = None
    engine: dict[Name, EngineParam] = Field(default_factory=dict, max_length=32)


class Control(Message):
    """V->* and *->S: run control. `step` advances `n_steps` while paused; `seek`, `speed` and
    `loop` steer trajectory replay."""

    type: Literal["control"] = "control"
    action: ControlAction
    n_steps: Annotated[int, Field(ge=1, le=1_000_000)] = 1
    frame: Annotated[int, Field(ge=0)] | None = None
    speed: Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)] | None = None
    loop: bool | None = None

    @model_validator(mode="after")
    def _arguments(self) -> Self:
        need = {"seek": "frame", "speed": "speed", "loop": "loop"}.get(self.action)
        if need is not None and getattr(self, need) is None:
            raise ValueError(f"action {self.action!r} needs field {need!r}")
        return self


class Forces(Message):
    """*->S (or a script's V->*): external forces on atoms, kJ/mol/A; empty clears all."""

    type: Literal["forces"] = "forces"
    indices: AtomInts
    forces: Positions

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        if self.indices.shape[0] != self.forces.shape[0]:
            raise ValueError("indices and forces differ in length")
        if self.indices.count and int(self.indices.to_numpy().min()) < 0:
            raise ValueError("negative atom index")
        return self


SimSteering = SimParams | Control | Forces
"""*->S: what steers a simulation; the server forwards it, the simulation answers each with a
`params_ack`."""


class Pull(Message):
    """V->*: pull one atom with a spring toward `target` (angstrom), or apply `force`
    directly; `release` clears it."""

    type: Literal["pull"] = "pull"
    atom: Annotated[int, Field(ge=0)]
    target: Point | None = None
    force: Vec3 | None = None
    spring_k: Annotated[float, Field(gt=0, le=10_000, allow_inf_nan=False)] = 10.0
    max_force: Annotated[float, Field(gt=0, le=100_000, allow_inf_nan=False)] = 1000.0
    release: bool = False

    @model_validator(mode="after")
    def _one_of(self) -> Self:
        if not self.release and (self.target is None) == (self.force is None):
            raise ValueError("give exactly one of target or force, or release")
        return self


# ---------------------------------------------------------------- view and rendering (V <-> *)


class Camera(Model):
    """Orbit camera: looks at `target` from `distance` along the orientation's +z axis.

    `orientation` is a unit quaternion (w, x, y, z) rotating camera space into world space.
    """

    target: Vec3 = (0.0, 0.0, 0.0)
    distance: CameraLength = 50.0
    orientation: tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat] = (1.0, 0.0, 0.0, 0.0)
    projection: Literal["perspective", "orthographic"] = "perspective"
    fov_deg: Annotated[float, Field(gt=1, lt=170, allow_inf_nan=False)] = 40.0
    ortho_height: CameraLength = 40.0

    @model_validator(mode="after")
    def _unit_quaternion(self) -> Self:
        n = sum(q * q for q in self.orientation) ** 0.5
        if not 0.5 < n < 2.0:
            raise ValueError(f"orientation must be a unit quaternion, norm is {n:.3g}")
        return self


class View(Message):
    """V->*: this viewer's camera and canvas size; `interacting` lowers quality while moving."""

    type: Literal["view"] = "view"
    camera: Camera | None = None
    """This viewer's own camera; None: the session's (`state.camera`, which frames the
    molecule, and follows it when the session refits)."""
    width: Annotated[int, Field(ge=1)] = 640
    height: Annotated[int, Field(ge=1)] = 480
    device_pixel_ratio: Annotated[float, Field(gt=0, le=8, allow_inf_nan=False)] = 1.0
    interacting: bool = False
    track: list[Annotated[int, Field(ge=0)]] = Field(default_factory=list, max_length=32)
    """Atoms whose positions this viewer wants with each new frame (`tracked` messages)."""
    video: list[VideoCodec] = Field(default_factory=list, max_length=8)
    """Video codecs this viewer decodes at this size (WebCodecs `isConfigSupported`), best
    first by its own taste; empty: JPEG images only. The server streams the best codec it can
    encode and acknowledges nothing: the viewer learns the choice from `image.format`."""


class TFPoint(Model):
    """Transfer-function control point: density `x` (in iso-level units) -> colour, opacity."""

    x: NonNegFloat
    color: RGB = (1.0, 1.0, 1.0)
    alpha: Unit = 0.0


class Lighting(Model):
    ambient: Unit = 0.25
    diffuse: Unit = 0.7
    specular: Unit = 0.35
    shininess: Annotated[float, Field(ge=1, le=512, allow_inf_nan=False)] = 32.0
    key_light: bool = True
    ambient_occlusion: bool = False
    depth_cue: Unit = 0.0


ScaleSpace = Literal["classical", "geodesic", "carved", "warped"]
"""`"warped"` is the name 1.1-1.7 gave `"carved"`, kept so saved views and recordings open."""
ColorBy = Literal["element", "residue", "chain", "uniform", "bfactor", "charge", "motion"]
TFPreset = Literal["cloud", "shells", "iso-like"]
Periodic = Literal["off", "whole", "wrap", "molecules", "unwrap"]
AUTO_CENTER = "protein or nucleic"
"""What `center: "auto"` centres on (when a boxed frame has such atoms)."""


MAX_LAYERS = 8
MIN_CUTOFF_SIGMAS = 1
MAX_CUTOFF_SIGMAS = 6
"""The range of `RenderParams.cutoff_sigmas`, the greatest reach of an atom's Gaussian in
sigmas; the renderer refuses the same range (the surface's accuracy needs at most 4)."""
LAYER_OVERRIDES = (
    "mode", "sigma_A", "iso_level", "scale_space", "color_by", "uniform_color", "tf_preset",
    "transfer_function",
)  # fmt: skip
SelectionText = Annotated[str, Field(min_length=1, max_length=2048)]


class Layer(Model):
    """One part of the system drawn its own way: the atoms `selection` names (MDAnalysis
    selection language, evaluated on the server against the session's topology) at their own
    scale. A field left None takes the session's value (`RenderParams`), so a client that
    only knows the single-layer fields still steers every layer that does not set its own."""

    name: Annotated[str, Field(max_length=64)] = ""
    selection: SelectionText = "all"
    visible: bool = True
    mode: Literal["iso", "volume", "licorice", "tube"] | None = None
    """`licorice`: atoms and bonds as sticks; `tube`: a tube through the CA / P trace; both
    drawn as solid shapes in the same image as the density layers."""
    radius_A: Annotated[float, Field(gt=0, le=10, allow_inf_nan=False)] | None = None
    """The stick (licorice, default 0.25 A) or tube (default 0.6 A) radius."""
    sigma_A: Annotated[float, Field(ge=0.05, le=50, allow_inf_nan=False)] | None = None
    iso_level: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] | None = None
    scale_space: ScaleSpace | None = None
    color_by: ColorBy | None = None
    uniform_color: RGB | None = None
    tf_preset: TFPreset | None = None
    transfer_function: Annotated[list[TFPoint], Field(max_length=64)] | None = None
    """A cloud layer's own transfer function (control points as in `RenderParams`)."""
    opacity: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] = 1.0
    """Below 1 the layer is translucent: it blends over what lies behind it, in depth order."""

    def overrides(self) -> dict[str, Any]:
        """The session fields this layer sets for itself (a shape mode is not a density's)."""
        out = {k: getattr(self, k) for k in LAYER_OVERRIDES if getattr(self, k) is not None}
        if out.get("mode") not in (None, "iso", "volume"):
            del out["mode"]
        return out


class RenderParams(Model):
    """How the density is built and shown; shared by every viewer of a session.

    `iso_level` (and the transfer function's x) are fractions of the density's own scale,
    the mean density at the atoms at this sigma (`level_scale="mean"`), so the surface stays
    near the molecule's extent as sigma grows; `level_scale="absolute"` reads them in units of
    one atom's peak density instead. `scale_space="geodesic"` draws the thesis's warped density
    (distances measured through the bond graph, made smooth: `geodesic_smoothing` sigmas round
    its creases), `"carved"` a Gaussian density carved away from the bond skeleton
    (docs/rendering.md); `warp_strength` 0 is the classical density in both."""

    mode: Literal["iso", "volume"] = "iso"
    sigma_A: Annotated[float, Field(ge=0.05, le=50, allow_inf_nan=False)] = 1.5
    radius_mode: Literal["uniform", "vdw"] = "uniform"
    iso_level: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] = 0.25
    cutoff_sigmas: Annotated[
        float, Field(ge=MIN_CUTOFF_SIGMAS, le=MAX_CUTOFF_SIGMAS, allow_inf_nan=False)
    ] = 4.0
    step_sigmas: Annotated[float, Field(ge=0.02, le=2, allow_inf_nan=False)] = 0.25
    transfer_function: list[TFPoint] = Field(default_factory=list, max_length=64)
    tf_preset: TFPreset = "cloud"
    color_by: ColorBy = "element"
    uniform_color: RGB = (0.85, 0.85, 0.9)
    lighting: Lighting = Lighting()
    background: RGB = (0.08, 0.09, 0.11)
    quality: Annotated[float, Field(ge=0.1, le=2, allow_inf_nan=False)] = 1.0
    jpeg_quality: Annotated[int, Field(ge=10, le=100)] = 85
    scale_space: ScaleSpace = "classical"
    warp_strength: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] = 1.0
    geodesic_smoothing: Annotated[float, Field(ge=0.05, le=2, allow_inf_nan=False)] = 0.6
    """tau / sigma of the geodesic density: the temperature of its soft minimum over routes
    (smaller is closer to the thesis's creased field, larger smoother)."""
    density_weights: Literal["uniform", "electrons"] = "uniform"
    level_scale: Literal["mean", "absolute"] = "mean"
    time_smoothing: Literal["off", "classical", "warped"] = "off"
    """Temporal scale: each atom's path smoothed over the last `time_window` frames with a
    Gaussian of `tau_frames`, in frames (`classical`) or in the arclength of the atom's path
    (`warped`, eq. 3.3), which keeps sudden moves sharp."""
    tau_frames: Annotated[float, Field(ge=0.1, le=32, allow_inf_nan=False)] = 3.0
    time_window: Annotated[int, Field(ge=1, le=64)] = 16
    time_warp_per_A: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 1.0
    """Warp strength: how many frames of warped time one angstrom of motion counts as."""
    time_kernel: Literal["auto", "causal", "centred"] = "auto"
    """`causal` uses past frames only (the newest frame shown); `centred` frames on both sides
    (shown `(time_window - 1) // 2` frames late); `auto`: centred for replays, else causal."""
    rigid_fit: bool = False
    """Remove the molecule's rigid-body motion before smoothing (a tumbling molecule is not
    smeared): each frame is fitted onto the window's first on its heavy atoms."""
    layers: list[Layer] = Field(default_factory=list, max_length=MAX_LAYERS)
    """Parts of the system each drawn at its own scale, in one image (surfaces occlude each
    other, translucent layers blend in depth order); empty: every atom, with the fields above.
    A patch that names `layers` replaces the whole list."""
    periodic: Periodic = "molecules"
    """How a frame with a periodic box is shown (a frame without one is drawn as sent):
    `whole` joins every molecule the box cuts (bonds from the topology); `molecules` also puts
    each molecule's centre of geometry in the box; `wrap` puts every atom in the box; `unwrap`
    follows every atom across the box from frame to frame (molecules whole at the first);
    `off` draws the positions as sent. One transform for the whole system: layers share it."""
    center: Literal["off", "auto", "selection"] = "auto"
    """Whose centre of geometry is moved to the centre of the box: `auto` the protein and
    nucleic acids of a boxed frame that has some (else nothing), `selection` the atoms of
    `center_selection` (a frame without a box: moved to the origin)."""
    center_selection: SelectionText = "protein"
    fit: Literal["off", "translation", "rotation"] = "off"
    """Superpose every frame on a reference frame by `fit_selection` (after the box steps):
    `rotation` rotates and translates it (least squares), `translation` only translates it.
    The reference is the first frame drawn with this fit (in a file, its first frame)."""
    fit_selection: SelectionText = "backbone"
    show_cell: bool = False
    """Draw the periodic box as an outline (a frame without a box has none)."""

    def needs_history(self) -> bool:
        """Whether a render needs the last frames too (smoothing over time, motion colours)."""
        return self.time_smoothing != "off" or self.color_by == "motion"


def _partial(model: type[Model], name: str) -> type[Model]:
    """`model` with every field optional (None: not set), keeping each field's constraints;
    nested models become partial too, so a patch names only the leaves it changes."""
    fields: dict[str, Any] = {}
    for key, info in model.model_fields.items():
        kind: Any = info.annotation
        if isinstance(kind, type) and issubclass(kind, Model):
            kind = _partial(kind, f"{kind.__name__}Patch")
        if info.metadata:
            kind = Annotated[kind, *info.metadata]
        fields[key] = (kind | None, None)
    return create_model(name, __base__=Model, __doc__=f"A partial {model.__name__}.", **fields)


if TYPE_CHECKING:
    RenderParamsPatch = RenderParams
else:
    RenderParamsPatch = _partial(RenderParams, "RenderParamsPatch")


class SetRenderParams(Message):
    """V->*: change render parameters; only the fields present in `params` change."""

    type: Literal["render_params"] = "render_params"
    params: RenderParamsPatch

    def changes(self) -> dict[str, Any]:
        """The fields the sender set, nested models included (a partial `lighting` names only
        the lighting fields it changes)."""
        return self.params.model_dump(exclude_none=True)


class Pick(Message):
    """V->*: which atom is under pixel (x, y) of this viewer's last image?"""

    type: Literal["pick"] = "pick"
    x: Annotated[int, Field(ge=0)]
    y: Annotated[int, Field(ge=0)]


class Picked(Message):
    """*->V: the answer to `pick` (`ref`); `atom` is None over the background."""

    type: Literal["picked"] = "picked"
    ref: Seq | None = None
    atom: Annotated[int, Field(ge=0)] | None = None
    element: str = ""
    name: str = ""
    residue_id: int = 0
    residue_name: str = ""
    chain: str = ""
    position: Vec3 | None = None
    depth: FiniteFloat | None = None
    layer: Annotated[str, Field(max_length=64)] = ""
    """The name of the layer the atom was picked in (empty without layers)."""


class Select(Message):
    """V->*: how many atoms does `text` select now? (Checked as a layer would be; nothing
    changes.) Answered by `selected`."""

    type: Literal["select"] = "select"
    text: Annotated[str, Field(max_length=2048)]


class Selected(Message):
    """*->V: the answer to `select` (`ref`): the atom count, or why the text is invalid and
    where (`position`, a 0-based character offset)."""

    type: Literal["selected"] = "selected"
    ref: Seq | None = None
    text: Annotated[str, Field(max_length=2048)] = ""
    count: Annotated[int, Field(ge=0)] | None = None
    error: Annotated[str, Field(max_length=1024)] = ""
    position: Annotated[int, Field(ge=0)] | None = None
    dynamic: bool = False


class Image(Message):
    """*->V: one encoded image. `ref` is the seq of the viewer message it answers, if any."""

    type: Literal["image"] = "image"
    ref: Seq | None = None
    frame_id: Annotated[int, Field(ge=0)]
    step: Annotated[int, Field(ge=0)] | None = None
    format: ImageFormat
    data: bytes
    width: Annotated[int, Field(ge=1)]
    height: Annotated[int, Field(ge=1)]
    still: bool = True
    render_ms: NonNegFloat = 0.0
    encode_ms: NonNegFloat = 0.0
    server_time: FiniteFloat = 0.0
    histogram: Floats | None = None
    codec: Annotated[str, Field(max_length=64)] | None = None
    """Video only: the WebCodecs codec string of the stream (`avc1.640033`, `av01.0.13M.08`,
    ...); H.264 is Annex B with its parameter sets in every keyframe."""
    key: bool | None = None
    """Video only: a keyframe (the viewer's decoder can start here)."""
    stream: Annotated[int, Field(ge=0)] | None = None
    """Video only: which stream this frame belongs to; a new stream starts with a keyframe and
    the viewer configures a fresh decoder for it."""
    bitrate_kbps: NonNegFloat | None = None
    """Video only: the bit rate the stream is encoded at (adapted to this viewer's link)."""
    encoder: Annotated[str, Field(max_length=64)] | None = None
    """Video only: the encoder (`libx264`, `h264_nvenc`, ...)."""


class FrameAck(Message):
    """V->*: a video frame was decoded and drawn. The server measures each viewer's link with
    these (round trip, frames and bytes in flight) and adapts its bit rate and frame rate."""

    type: Literal["frame_ack"] = "frame_ack"
    frame_id: Annotated[int, Field(ge=0)]
    decode_ms: NonNegFloat = 0.0


class ClientInfo(Model):
    client_id: str
    role: Role
    client: str = ""


class SimStatus(Model):
    state: Literal["waiting", "running", "paused", "disconnected"] = "waiting"
    step: int = 0
    time_ps: FiniteFloat = 0.0
    steps_per_s: NonNegFloat = 0.0
    n_atoms: int = 0
    engine: str = ""
    observables: dict[Name, FiniteFloat] = Field(default_factory=dict)


class LegendEntry(Model):
    label: Annotated[str, Field(max_length=64)]
    color: RGB


class Legend(Model):
    """What the colours of the current `color_by` mean: named swatches, or a ramp from `low` to
    `high` (in `unit`)."""

    color_by: ColorBy
    entries: list[LegendEntry] = Field(default_factory=list, max_length=64)
    ramp: list[RGB] = Field(default_factory=list, max_length=16)
    low: FiniteFloat | None = None
    high: FiniteFloat | None = None
    unit: Annotated[str, Field(max_length=16)] = ""


class Cell(Model):
    """The periodic box as displayed (moved with the frame by the fit): a corner and its three
    edges, angstrom."""

    origin: Vec3
    vectors: tuple[Vec3, Vec3, Vec3]


class Tracked(Message):
    """*->V: where the atoms a viewer tracks (`view.track`) are, at `step`; sent with new frames,
    at most every `state_interval_s`, so markers, labels and measurements follow the atoms."""

    type: Literal["tracked"] = "tracked"
    step: Annotated[int, Field(ge=0)] | None = None
    atoms: list[Annotated[int, Field(ge=0)]] = Field(default_factory=list, max_length=32)
    positions: list[Point] = Field(default_factory=list, max_length=32)


class State(Message):
    """*->V: changed parts of the shared session state; absent fields did not change."""

    type: Literal["state"] = "state"
    ref: Seq | None = None
    """The seq of the `render_params` message this state answers, sent by `by`: with the
    parameters it made, or with none when they were already in effect. The session applies a
    client's messages in order, so every one that client sent before `ref` has been applied
    or refused (an `error` names it) by then."""
    by: Name | None = None
    """The `client_id` of the client whose `render_params` message made this change (message
    `ref`, when it was numbered)."""
    render_params: RenderParams | None = None
    sim_params: SimParams | None = None
    sim: SimStatus | None = None
    clients: list[ClientInfo] | None = None
    """Everyone in the session: sent whole when a client joins, then as `joined`/`left`."""
    joined: list[ClientInfo] | None = None
    """Clients that joined since the last roster message."""
    left: list[Name] | None = None
    """`client_id`s of clients that left since the last roster message."""
    pulling: list[Pull] | None = None
    engine: EngineInfo | None = None
    """What the session's simulation can be steered with (see `EngineInfo`)."""
    legend: Legend | None = None
    """What the colours mean (sent when the topology or the colouring changes)."""
    camera: Camera | None = None
    """The session's default camera (framing the molecule), for viewers without their own."""
    cell: Cell | None = None
    """The periodic box of the frame shown (sent with the simulation's status when it
    changes), for drawing it as an outline (`render_params.show_cell`)."""


class Stats(Message):
    """*->V: render and delivery statistics, about once a second."""

    type: Literal["stats"] = "stats"
    render_fps: NonNegFloat = 0.0
    render_ms: NonNegFloat = 0.0
    encode_ms: NonNegFloat = 0.0
    grid_ms: NonNegFloat = 0.0
    upload_ms: NonNegFloat = 0.0
    frames_sent: int = 0
    frames_dropped: int = 0
    sim_frames: int = 0
    device: str = ""
    device_ms: dict[Name, NonNegFloat] = Field(default_factory=dict, max_length=16)
    """Render time of each device when one image is rendered across several."""


class Ping(Message):
    """Either way: echo request for latency and liveness."""

    type: Literal["ping"] = "ping"
    client_time: FiniteFloat = 0.0


class Pong(Message):
    type: Literal["pong"] = "pong"
    ref: Seq | None = None
    client_time: FiniteFloat = 0.0
    server_time: FiniteFloat = 0.0


class Error(Message):
    """Either way: a rejected message. `path` names the field, `ref` echoes its seq."""

    type: Literal["error"] = "error"
    code: ErrorCode
    message: Annotated[str, Field(max_length=4096)]
    path: str | None = None
    ref: Seq | None = None


AnyMessage = Annotated[
    Hello
    | Welcome
    | Topology
    | Frame
    | ParamsAck
    | SimParams
    | Control
    | Forces
    | Pull
    | View
    | SetRenderParams
    | Pick
    | Picked
    | Select
    | Selected
    | Image
    | FrameAck
    | State
    | Stats
    | Ping
    | Pong
    | Error
    | EngineInfo
    | Event
    | Tracked,
    Field(discriminator="type"),
]

MESSAGE_TYPES: dict[str, type[Message]] = {
    m.model_fields["type"].default: m
    for m in (
        Hello,
        Welcome,
        Topology,
        Frame,
        ParamsAck,
        SimParams,
        Control,
        Forces,
        Pull,
        View,
        SetRenderParams,
        Pick,
        Picked,
        Select,
        Selected,
        Image,
        FrameAck,
        State,
        Stats,
        Ping,
        Pong,
        Error,
        EngineInfo,
        Event,
        Tracked,
    )
}

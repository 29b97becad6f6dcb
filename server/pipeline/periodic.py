"""The periodic options of renders outside a live session (REST renders of files, jobs, Ray
chunks, `scalesteer render`): the centre and fit selections of one parameter set evaluated
once per topology, and which frames of a file a display needs.

A file's frames are displayed as a live session's are (`server.render.periodic`), with one
difference: the fit's reference is the file's first frame, whatever frames are drawn, so two
renders of the same file (a zip and a movie, chunks on Ray) superpose alike.
"""

from __future__ import annotations

import asyncio
from concurrent.futures import Future
from typing import Any

import numpy as np
import numpy.typing as npt

import protocol as p
from server.pipeline.selections import Selections
from server.render.boxes import Options, Shown, usable_box
from structures.selection import SelectionError, check_syntax, is_dynamic
from structures.selection_cost import SelectionLimits
from structures.selection_pool import Result

PERIODIC_FIELDS = ("periodic", "center", "center_selection", "fit", "fit_selection")
"""The render parameters that change how frames are displayed."""
REFERENCE_FRAME = 0
"""The frame of a file a fit superposes every frame onto."""


class PeriodicError(ValueError):
    """A centre or fit selection that cannot be used: `path` names its field."""

    def __init__(self, path: str, reason: str) -> None:
        self.path = path
        self.reason = reason
        super().__init__(f"{path}: {reason}")


def selection_fields(params: p.RenderParams) -> list[tuple[str, str]]:
    """(field, selection text) of the selections these parameters centre or fit on."""
    used = []
    if params.center == "selection":
        used.append(("center_selection", params.center_selection))
    if params.fit != "off":
        used.append(("fit_selection", params.fit_selection))
    return used


MIN_ROTATION_ATOMS = 3
"""A rotation fit on fewer atoms (or on atoms along one line) is undetermined."""
TRANSLATION_FIT = "fit 'translation'"
"""How a refusal names the fit that takes one atom (a command line names its own option)."""


def atoms_problem(field: str, text: str, count: int, params: p.RenderParams) -> str | None:
    """Why a centre or fit selection that matched `count` atoms cannot be used (None: it
    can): it matches nothing, or too few atoms to fix a rotation."""
    if count == 0:
        return f"{text!r} matches no atom"
    if field == "fit_selection" and params.fit == "rotation" and count < MIN_ROTATION_ATOMS:
        return (
            f"{text!r} matches {count} atom{'s' if count > 1 else ''}; a rotation fit needs at "
            f"least {MIN_ROTATION_ATOMS} ({TRANSLATION_FIT} takes one)"
        )
    return None


def check_periodic(params: p.RenderParams, limits: SelectionLimits | None = None) -> None:
    """Raise PeriodicError naming the centre or fit selection that does not parse (or crosses
    `limits`), or that reads coordinates (the centre and the fit need fixed atoms)."""
    for field, text in selection_fields(params):
        try:
            check_syntax(text, limits)
        except SelectionError as exc:
            raise PeriodicError(field, str(exc)) from None
        if is_dynamic(text):
            raise PeriodicError(
                field,
                f"{text!r} reads coordinates (around, point, ...); the centre and the fit need "
                "atoms that stay the same from frame to frame",
            )


def needs_selections(params: p.RenderParams) -> bool:
    """Whether displaying frames may need a selection evaluated (the centre or the fit)."""
    return params.center != "off" or params.fit != "off"


def needs_display(params: p.RenderParams, box: npt.NDArray[Any] | None) -> bool:
    """Whether a frame with this box is displayed other than as read."""
    if usable_box(box) is not None and (params.periodic != "off" or params.center != "off"):
        return True
    return params.fit != "off" or params.center == "selection"


class PeriodicOptions:
    """The periodic options of one parameter set on one topology, its selections evaluated
    once (by `selections`: a selection worker, or `InProcess`)."""

    def __init__(self, params: p.RenderParams, selections: Selections | None) -> None:
        self.params = params
        self.selections = selections
        self._atoms: dict[str, npt.NDArray[np.int32]] = {}

    def texts(self, boxed: bool) -> tuple[str | None, str | None]:
        params = self.params
        centre = None
        if params.center == "selection":
            centre = params.center_selection
        elif params.center == "auto" and boxed:
            centre = p.AUTO_CENTER
        return centre, params.fit_selection if params.fit != "off" else None

    def _missing(self, boxed: bool) -> list[str]:
        return [t for t in self.texts(boxed) if t is not None and t not in self._atoms]

    def _submit(self, texts: list[str]) -> Future[list[Result]]:
        assert self.selections is not None, "centre and fit selections need an evaluator"
        return self.selections.submit(texts)

    def _take(self, texts: list[str], found: list[Result]) -> None:
        fields = dict((t, f) for f, t in selection_fields(self.params))
        for text, result in zip(texts, found, strict=True):
            if isinstance(result, SelectionError):
                if text == p.AUTO_CENTER:  # `auto` on a system it cannot read: no centre
                    self._atoms[text] = np.zeros(0, np.int32)
                    continue
                raise PeriodicError(fields.get(text, "center_selection"), result.reason)
            self._atoms[text] = np.asarray(result, dtype=np.int32)
        for field, text in selection_fields(self.params):  # those the user named
            atoms = self._atoms.get(text)
            problem = None if atoms is None else atoms_problem(field, text, len(atoms), self.params)
            if problem is not None:
                raise PeriodicError(field, problem)

    def _options(self, boxed: bool) -> Options:
        centre_text, fit_text = self.texts(boxed)
        centre = self._atoms.get(centre_text) if centre_text else None
        fit = self._atoms.get(fit_text) if fit_text else None
        return Options(
            mode=self.params.periodic if boxed else "off",
            centre=centre if centre is not None and len(centre) else None,
            fit=self.params.fit if fit is not None and len(fit) else "off",
            fit_atoms=fit if fit is not None and len(fit) else None,
        )

    def get(self, box: npt.NDArray[Any] | None) -> Options:
        """The options for a frame with this box (evaluating, and waiting, when needed);
        raises PeriodicError for a selection that cannot be used."""
        boxed = usable_box(box) is not None
        missing = self._missing(boxed)
        if missing:
            try:
                found = self._submit(missing).result()
            except SelectionError as exc:
                raise PeriodicError(missing[0], str(exc)) from None
            self._take(missing, found)
        return self._options(boxed)

    async def get_async(self, box: npt.NDArray[Any] | None) -> Options:
        """`get`, awaited on the event loop (the evaluation runs in a worker)."""
        boxed = usable_box(box) is not None
        missing = self._missing(boxed)
        if missing:
            try:
                found = await asyncio.wrap_future(self._submit(missing))
            except SelectionError as exc:
                raise PeriodicError(missing[0], str(exc)) from None
            self._take(missing, found)
        return self._options(boxed)


def displayed_cell(shown: Shown | None, box: npt.NDArray[Any] | None) -> p.Cell | None:
    """The periodic box of a frame as displayed (moved with it by a fit), or None without one."""
    if shown is not None and shown.cell is not None:
        origin, vectors = shown.cell
    else:
        cell = usable_box(box)
        if cell is None:
            return None
        origin, vectors = np.zeros(3), cell

    def point(v: npt.NDArray[Any]) -> tuple[float, float, float]:
        return (round(float(v[0]), 4), round(float(v[1]), 4), round(float(v[2]), 4))

    return p.Cell(origin=point(origin), vectors=(point(vectors[0]), point(vectors[1]),
                                                 point(vectors[2])))  # fmt: skip

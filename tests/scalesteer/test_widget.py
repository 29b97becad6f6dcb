"""The notebook widget's Python side against a real server: its traitlets steer the session and
follow it, several widgets share one session, and each has its own stream of pictures. (The page
side runs in a real JupyterLab: tests/browser/test_notebook.py.)"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import pytest
import traitlets

import scalesteer
from scalesteer import ScalesteerError

pytest.importorskip("anywidget")


def eventually(predicate: Callable[[], Any], timeout: float = 20.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError("not reached in time")


def test_traits_steer_the_session_and_follow_it(
    client: scalesteer.Client, small_universe: Any
) -> None:
    session = client.open(small_universe, frame=0)
    view, other = session.view(160, 120), session.view(120, 90)
    view.sigma = 3.0
    assert session.render_params.sigma_A == 3.0
    eventually(lambda: other.sigma == 3.0)  # the second widget shows the change
    view.scale_space = "geodesic"
    view.iso = 0.4
    params = session.render_params
    assert (params.scale_space, params.iso_level) == ("geodesic", 0.4)
    elsewhere = client.session(session.name)  # another steerer (the dashboard, a script)
    elsewhere.set(sigma_A=5.0, mode="volume")
    eventually(lambda: view.sigma == 5.0 and other.sigma == 5.0 and view.mode == "volume")
    assert session.render_params.sigma_A == 5.0, "the server's change is not steered back"


def test_a_bad_value_is_refused_and_the_trait_keeps_the_sessions(
    client: scalesteer.Client, small_universe: Any
) -> None:
    session = client.open(small_universe, frame=0)
    view = session.view(160, 120)
    with pytest.raises(traitlets.TraitError, match=r"render_params\.sigma_A"):
        view.sigma = -2.0
    assert view.sigma == 1.5 and session.render_params.sigma_A == 1.5
    with pytest.raises(traitlets.TraitError, match="scale_space"):
        view.scale_space = "fourier"
    with pytest.raises(traitlets.TraitError, match=r"render_params\.params\.layers\.0\.colour"):
        view.layers = [{"name": "misspelt", "selection": "protein", "colour": "red"}]
    assert view.layers == []
    with pytest.raises(ScalesteerError) as refused:  # only the server can tell
        view.layers = [{"name": "typo", "selection": "resname"}]
    assert refused.value.path == "render_params.params.layers.0.selection"
    assert view.layers == [] and session.layers == []
    view.layers = [{"name": "backbone", "selection": "backbone", "mode": "tube"}]
    assert [lay.selection for lay in session.layers] == ["backbone"]


def test_each_widget_has_its_own_stream_and_camera(
    client: scalesteer.Client, small_universe: Any
) -> None:
    session = client.open(small_universe, frame=0)
    view = session.view(160, 120)
    eventually(lambda: view.images_sent >= 1, timeout=60)
    assert view.session_camera is not None
    turned = dict(view.session_camera, orientation=[0.0, 0.0, 1.0, 0.0])
    view.camera = turned
    with pytest.raises(traitlets.TraitError, match="camera"):
        view.camera = dict(turned, distance=-1)
    sent = view.images_sent
    eventually(lambda: view.images_sent > sent, timeout=60)  # the turned camera is drawn
    assert widgets(client, session.name) == 1
    view.close()
    assert view.link.closed == "closed"
    eventually(lambda: widgets(client, session.name) == 0)


def widgets(client: scalesteer.Client, name: str) -> int:
    """The widgets' connections in session `name`, as the server lists its clients."""
    summary = next(s for s in client.sessions() if s["id"] == name)
    return sum(c["client"] == "scalesteer-widget" for c in summary["clients"])


def test_the_widget_loads_every_module_the_viewport_imports_before_it() -> None:
    """The viewport came to import cell.js and labels.js, which the widget did not load: it
    showed no picture. Each module now comes after every module it imports."""
    import re

    from scalesteer.widget import ENTRIES, dashboard_modules

    names = [name for name, _ in dashboard_modules()]
    assert set(ENTRIES) <= set(names) and {"cell.js", "labels.js"} <= set(names)
    for i, (name, source) in enumerate(dashboard_modules()):
        for imported in re.findall(r"""from\s*["']\./([\w.-]+\.js)["']""", source):
            assert imported in names[:i], f"{name} imports {imported} before it is loaded"

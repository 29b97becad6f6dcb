"""What `make demo` installs is enough for every path the README and docs/ document for it."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def extra(name: str) -> set[str]:
    """The distributions an extra pulls in, its nested `scalesteer[...]` extras expanded."""
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    out: set[str] = set()
    for requirement in extras[name]:
        nested = re.fullmatch(r"scalesteer\[([\w,-]+)\]", requirement)
        if nested:
            for inner in nested.group(1).split(","):
                out |= extra(inner)
        else:
            out.add(re.split(r"[<>=!;\[ ]", requirement, maxsplit=1)[0].lower())
    return out


def test_the_demo_extra_installs_what_its_documented_features_need() -> None:
    demo = extra("demo")
    # the server, OpenMM, trajectory files and MP4 jobs (docs/server.md: `output=mp4`)
    assert {"fastapi", "uvicorn", "warp-lang", "openmm", "mdanalysis", "av"} <= demo


def test_the_mp4_job_documented_in_the_server_docs_needs_only_the_demo_extra() -> None:
    assert "output=mp4" in (ROOT / "docs" / "server.md").read_text()
    import av  # installed by the demo extra, as asserted above

    assert av.codec.Codec("libx264", "w").name == "libx264"


def test_the_notebook_extra_installs_the_client_and_the_widget() -> None:
    # docs/python.md: `pip install -e '.[notebook]'` is all the three-line start needs
    assert {"httpx", "pillow", "anywidget", "ipywidgets", "mdanalysis"} <= extra("notebook")
    # and `make test` (the dev extra) runs the widget in JupyterLab and the example notebooks
    assert {"anywidget", "jupyterlab", "nbclient", "ipykernel", "mdtraj", "ase"} <= extra("dev")

"""The Python client against a real server (in-process, loopback, CPU device)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

import scalesteer
from tests.conftest import LiveServer


@pytest.fixture
def client(live_server: LiveServer) -> Iterator[scalesteer.Client]:
    c = scalesteer.connect(live_server.url, live_server.token)
    yield c
    c.close()


@pytest.fixture
def universe() -> object:
    """The MDAnalysisTests adenylate kinase in water: 47,681 atoms, 10 frames (GRO/XTC)."""
    import MDAnalysis as mda
    from MDAnalysisTests.datafiles import GRO, XTC

    return mda.Universe(GRO, XTC)


@pytest.fixture
def small_universe() -> object:
    """A 3,341-atom protein with 98 frames (PSF/DCD): quick to play."""
    import warnings

    import MDAnalysis as mda
    from MDAnalysisTests.datafiles import DCD, PSF

    with warnings.catch_warnings():  # DCD's reader warns of the copies it makes
        warnings.simplefilter("ignore", DeprecationWarning)
        return mda.Universe(PSF, DCD)

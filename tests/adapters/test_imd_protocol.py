"""The IMD bridge against imdclient's in-thread IMD engine (v2 and v3, both byte orders) and
against raw sockets that break the protocol on purpose."""

from __future__ import annotations

import socket
import struct
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path

import MDAnalysis as mda
import numpy as np
import pytest
from imdclient.IMDClient import read_into_buf
from imdclient.IMDProtocol import IMDHeaderType, IMDSessionInfo
from imdclient.tests.server import InThreadIMDServer
from MDAnalysisTests.datafiles import PDB_multiframe

from protocol import Control, Event, Forces, SimParams, WireArray
from simulation_adapters import imd
from simulation_adapters.imd import BridgeError, IMDBridge, parse_address
from simulation_adapters.imd_session import IMDHandshakeError, IMDSession
from structures.reader import Structure, topology_of
from tests.adapters.sim_peer import SimPeer

N_ATOMS = 12
N_FRAMES = 6


def make_universe(
    n_atoms: int = N_ATOMS, n_frames: int = N_FRAMES, coords: np.ndarray | None = None
) -> mda.Universe:
    """Atoms with names and elements, and a trajectory the in-thread engine can send
    (box, time, velocities and forces included)."""
    u = mda.Universe.empty(n_atoms, trajectory=True)
    u.add_TopologyAttr("names", [f"C{i}" for i in range(n_atoms)])
    u.add_TopologyAttr("resnames", ["MOL"])
    u.add_TopologyAttr("elements", ["C"] * n_atoms)
    if coords is None:
        rng = np.random.default_rng(1)
        coords = rng.uniform(0, 20, size=(n_frames, n_atoms, 3)).astype(np.float32)
    ones = np.ones_like(coords)
    u.load_new(
        coords,
        order="fac",
        dimensions=[20.0, 21.0, 22.0, 90, 90, 90],
        dt=0.5,
        velocities=ones,
        forces=ones,
    )
    return u


def structure_of(u: mda.Universe) -> Structure:
    return Structure(topology=topology_of(u, guess_bonds=False), universe=u)


def session_info(version: int, endian: str) -> IMDSessionInfo:
    return IMDSessionInfo(
        version=version,
        endianness=endian,
        wrapped_coords=False,
        time=version == 3,
        energies=True,
        box=version == 3,
        positions=True,
        velocities=version == 3,
        forces=version == 3,
    )


class Engine:
    """imdclient's InThreadIMDServer plus a reader for what the bridge sends back."""

    def __init__(self, version: int, endian: str, u: mda.Universe) -> None:
        self.server = InThreadIMDServer(u.trajectory)
        self.server.set_imdsessioninfo(session_info(version, endian))
        self.endian = endian
        self.server.handshake_sequence("localhost", first_frame=False)

    @property
    def port(self) -> int:
        return int(self.server.port)

    def packet(self) -> tuple[IMDHeaderType, int, bytes]:
        head = bytearray(8)
        read_into_buf(self.server.conn, head)
        kind, length = struct.unpack("!ii", head)
        body = b""
        if IMDHeaderType(kind) is IMDHeaderType.IMD_MDCOMM:
            buf = bytearray(16 * length)
            read_into_buf(self.server.conn, buf)
            body = bytes(buf)
        return IMDHeaderType(kind), length, body

    def mdcomm(self, body: bytes, n: int) -> tuple[np.ndarray, np.ndarray]:
        idx = np.frombuffer(body[: 4 * n], dtype=f"{self.endian}i4")
        vec = np.frombuffer(body[4 * n :], dtype=f"{self.endian}f4").reshape(n, 3)
        return idx, vec


@pytest.fixture
def universe() -> mda.Universe:
    return make_universe()


@pytest.fixture
def bridges() -> Iterator[list[IMDBridge]]:
    made: list[IMDBridge] = []
    yield made
    for bridge in made:
        bridge.close()


def start_bridge(
    bridges: list[IMDBridge], engine_port: int, structure: Structure, peer: SimPeer, **kw: object
) -> IMDBridge:
    bridge = IMDBridge(
        "localhost", engine_port, structure, peer.ws_url, "secret", handshake_timeout=5, **kw
    )
    bridges.append(bridge)
    return bridge.start()


def forces_msg(indices: list[int], vectors: list[list[float]]) -> Forces:
    return Forces(
        indices=WireArray.from_numpy(np.array(indices, dtype=np.int32), "<i4"),
        forces=WireArray.from_numpy(np.array(vectors, dtype=np.float32).reshape(-1, 3), "<f4"),
    )


@pytest.mark.parametrize("endian", ["<", ">"])
def test_v3_frames_and_steering(
    endian: str, universe: mda.Universe, peer: SimPeer, bridges: list[IMDBridge]
) -> None:
    engine = Engine(3, endian, universe)
    bridge = start_bridge(bridges, engine.port, structure_of(universe), peer)
    engine.server.join_accept_thread()
    engine.server.send_frames(0, N_FRAMES)
    frames = peer.wait_for(lambda: [f for f in peer.frames if f.step == N_FRAMES - 1])
    last = frames[-1]
    assert peer.topologies[0].n_atoms == N_ATOMS
    np.testing.assert_allclose(last.positions.to_numpy(), universe.trajectory[-1].positions)
    np.testing.assert_allclose(np.diag(last.box.to_numpy()), [20.0, 21.0, 22.0], rtol=1e-6)
    assert last.time_ps == pytest.approx(universe.trajectory[-1].time)
    # the in-thread engine sends energies (i, i+1, ...): temperature i+1, total i+2, potential i+3
    i = N_FRAMES - 1
    assert last.observables["temperature_K"] == pytest.approx(i + 1)
    assert last.observables["potential_kJmol"] == pytest.approx(i + 3)
    assert last.observables["kinetic_kJmol"] == pytest.approx(-1.0)

    seq = peer.send(forces_msg([2, 5], [[10.0, 0.0, 0.0], [0.0, 3e5, 0.0]]))
    kind, n, body = engine.packet()
    assert kind is IMDHeaderType.IMD_MDCOMM and n == 2
    idx, vec = engine.mdcomm(body, n)
    np.testing.assert_array_equal(idx, [2, 5])
    np.testing.assert_allclose(vec, [[10.0, 0.0, 0.0], [0.0, 50.0, 0.0]])  # kJ/mol/A, capped
    ack = peer.wait_ack(seq)
    assert ack.ok and ack.step == N_FRAMES - 1 and ack.applied["capped"] == 1
    # releasing atom 5 sends it an explicit zero
    peer.send(forces_msg([2], [[1.0, 2.0, 3.0]]))
    kind, n, body = engine.packet()
    idx, vec = engine.mdcomm(body, n)
    np.testing.assert_array_equal(idx, [2, 5])
    np.testing.assert_allclose(vec, [[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])

    peer.send(Control(action="pause"))
    assert engine.packet()[0] is IMDHeaderType.IMD_PAUSE
    peer.send(Control(action="pause"))  # v3 pause is idempotent: sent again, harmless
    assert engine.packet()[0] is IMDHeaderType.IMD_PAUSE
    peer.send(Control(action="resume"))
    assert engine.packet()[0] is IMDHeaderType.IMD_RESUME
    seq = peer.send(SimParams(frame_interval=25, temperature_K=310.0))
    assert engine.packet()[:2] == (IMDHeaderType.IMD_TRATE, 25)
    ack = peer.wait_ack(seq)
    assert not ack.ok and ack.applied == {"frame_interval": 25} and "temperature" in ack.detail
    seq = peer.send(Control(action="stop"))
    ack = peer.wait_ack(seq)
    assert not ack.ok and "--allow-kill" in ack.detail

    engine.server.disconnect()  # between frames: a clean end of the session
    assert bridge.wait(10) and bridge.error is None
    engine.server.cleanup()


def test_v2_big_endian_forces_in_kcal_and_toggle_pause(
    universe: mda.Universe, peer: SimPeer, bridges: list[IMDBridge]
) -> None:
    engine = Engine(2, ">", universe)
    bridge = start_bridge(bridges, engine.port, structure_of(universe), peer, allow_kill=True)
    engine.server.join_accept_thread()
    engine.server.send_frames(0, 3)
    last = peer.wait_for(lambda: [f for f in peer.frames if f.step == 2])[-1]
    np.testing.assert_allclose(last.positions.to_numpy(), universe.trajectory[2].positions)
    assert last.box is None and last.time_ps == 0.0  # v2 carries neither
    assert last.observables["potential_kJmol"] == pytest.approx(5 * 4.184)  # kcal -> kJ

    peer.send(forces_msg([0], [[4.184, 0.0, -8.368]]))
    kind, n, body = engine.packet()
    assert kind is IMDHeaderType.IMD_MDCOMM
    idx, vec = engine.mdcomm(body, n)
    np.testing.assert_array_equal(idx, [0])
    np.testing.assert_allclose(vec, [[1.0, 0.0, -2.0]], rtol=1e-6)  # kcal/mol/A, big-endian

    peer.send(Control(action="pause"))
    assert engine.packet()[0] is IMDHeaderType.IMD_PAUSE
    seq = peer.send(Control(action="pause"))  # a second v2 PAUSE would resume: not sent
    assert peer.wait_ack(seq).detail == "already paused"
    peer.send(Control(action="resume"))
    assert engine.packet()[0] is IMDHeaderType.IMD_PAUSE  # v2 resumes by toggling
    seq = peer.send(Control(action="resume"))
    assert peer.wait_ack(seq).detail == "not paused"
    seq = peer.send(Control(action="stop"))
    assert engine.packet()[0] is IMDHeaderType.IMD_KILL
    assert peer.wait_ack(seq).ok
    engine.server.cleanup()
    assert bridge.wait(10)


def test_atom_count_mismatch_is_a_clear_error(
    universe: mda.Universe, peer: SimPeer, bridges: list[IMDBridge]
) -> None:
    engine = Engine(3, "<", universe)
    bridge = start_bridge(bridges, engine.port, structure_of(make_universe(N_ATOMS - 3)), peer)
    engine.server.join_accept_thread()
    engine.server.send_frames(0, 1)
    assert bridge.wait(10)
    assert isinstance(bridge.error, BridgeError)
    assert f"coordinates for {N_ATOMS} atoms but the topology has {N_ATOMS - 3}" in str(
        bridge.error
    )
    engine.server.cleanup()


def test_nan_coordinates_pause_the_engine_and_tell_the_session(
    universe: mda.Universe, peer: SimPeer, bridges: list[IMDBridge]
) -> None:
    """The guard: a non-finite frame is not forwarded; the engine is paused (IMD cannot roll
    back), everyone is told, and the bridge stays up for the frames that follow."""
    coords = np.stack([ts.positions.copy() for ts in universe.trajectory])
    coords[1, 4] = np.nan
    bad = make_universe(coords=coords)
    engine = Engine(3, "<", bad)
    bridge = start_bridge(bridges, engine.port, structure_of(universe), peer)
    engine.server.join_accept_thread()
    engine.server.send_frames(0, 2)
    kind, _n, _body = engine.packet()
    assert kind is IMDHeaderType.IMD_PAUSE
    event = peer.wait_for(lambda: peer.of_type(Event))[0]
    assert event.code == "guard" and event.step == 1 and "non-finite" in event.message
    # events go out ahead of queued frames: frame 0 may come after the event
    peer.wait_for(lambda: [f for f in peer.frames if f.step == 0])
    assert bridge.guard_trips == 1
    engine.server.send_frames(2, 3)  # the engine goes on: so does the bridge
    peer.wait_for(lambda: [f for f in peer.frames if f.step == 2])
    assert [f.step for f in peer.frames] == [0, 2]  # frame 1 was never forwarded
    assert bridge.error is None
    engine.server.cleanup()


def test_engine_disconnecting_mid_frame_is_an_error(
    universe: mda.Universe, peer: SimPeer, bridges: list[IMDBridge]
) -> None:
    engine = Engine(3, "<", universe)
    bridge = start_bridge(bridges, engine.port, structure_of(universe), peer)
    engine.server.join_accept_thread()
    engine.server.send_frames(0, 1)
    peer.wait_frames(1)
    head = struct.pack("!ii", IMDHeaderType.IMD_TIME.value, 1)
    engine.server.conn.sendall(head + struct.pack("<ddq", 0.5, 1.0, 1)[:10])  # cut short
    engine.server.conn.close()
    assert bridge.wait(10)
    assert isinstance(bridge.error, BridgeError)
    assert "in the middle of a frame" in str(bridge.error)
    engine.server.cleanup()


# ---------------------------------------------------------------------- broken handshakes


class RawEngine:
    """A listening socket that answers a connection with exactly the bytes given."""

    def __init__(self, payload: bytes, close: bool = False) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.port = self.sock.getsockname()[1]
        self.payload, self.close_after = payload, close
        self.conn: socket.socket | None = None
        self.thread = threading.Thread(target=self._serve)
        self.thread.start()

    def _serve(self) -> None:
        self.conn, _ = self.sock.accept()
        self.conn.sendall(self.payload)
        if self.close_after:
            self.conn.close()

    def stop(self) -> None:
        self.thread.join(5)
        if self.conn is not None:
            self.conn.close()
        self.sock.close()


@pytest.mark.parametrize(
    ("payload", "close", "message"),
    [
        (struct.pack("!ii", 4, 7), False, "IMD version 7"),
        (struct.pack("!ii", 2, 3), False, "did not start with an IMD handshake"),
        (struct.pack("!ii", 4, 3) + struct.pack("!ii", 10, 5), False, "of 5 bytes, expected 7"),
        (struct.pack("!ii", 4, 3) + struct.pack("!ii", 12, 1), False, "instead of IMD v3"),
        (struct.pack("!ii", 4, 3) + struct.pack("!ii", 10, 7) + bytes(7), False, "coordinates"),
        (b"", False, "no IMD handshake"),
        (b"\x00\x00", True, "closed the connection during the IMD handshake"),
    ],
)
def test_broken_handshakes_are_clear_errors(payload: bytes, close: bool, message: str) -> None:
    raw = RawEngine(payload, close)
    try:
        with pytest.raises(IMDHandshakeError, match=message):
            IMDSession.connect("127.0.0.1", raw.port, 4, handshake_timeout=0.5)
    finally:
        raw.stop()


@pytest.mark.parametrize("endian", ["<", ">"])
def test_v3_handshake_in_either_byte_order(endian: str) -> None:
    version = struct.pack(f"{endian}i", 3)
    info = struct.pack("!ii", 10, 7) + bytes([1, 0, 1, 1, 1, 0, 0])
    raw = RawEngine(struct.pack("!i", 4) + version + info)
    try:
        session = IMDSession.connect("127.0.0.1", raw.port, 4, handshake_timeout=2)
        raw.thread.join(5)
        assert raw.conn is not None
        assert raw.conn.recv(8) == struct.pack("!ii", IMDHeaderType.IMD_GO.value, 0)
        assert (session.version, session.endian) == (3, endian)
        assert session.info.time and session.info.box and not session.info.velocities
        session.close()
    finally:
        raw.stop()


def test_nothing_listening_is_a_clear_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(Exception, match="cannot connect to the MD engine"):
        IMDSession.connect("127.0.0.1", port, 4, connect_timeout=0.3)


def test_parse_address() -> None:
    assert parse_address("localhost:8888") == ("localhost", 8888)
    assert parse_address("imd://10.0.0.2:9000") == ("10.0.0.2", 9000)
    assert parse_address(":8888") == ("localhost", 8888)
    for bad in ("localhost", "host:0", "host:abc", "host:70000"):
        with pytest.raises(ValueError):
            parse_address(bad)


# ---------------------------------------------------------------------- command line


def test_cli_bridges_until_the_engine_ends(
    tmp_path: Path, universe: mda.Universe, peer: SimPeer
) -> None:
    pdb = tmp_path / "mol.pdb"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the PDB writer notes the attributes it makes up
        universe.atoms.write(str(pdb))
    engine = Engine(3, "<", universe)
    argv = ["--connect", f"localhost:{engine.port}", "--topology", str(pdb)]
    argv += ["--url", peer.ws_url, "--token", "secret", "--session", "imd"]
    result: list[int] = []
    runner = threading.Thread(target=lambda: result.append(imd.main(argv)))
    runner.start()
    engine.server.join_accept_thread()
    engine.server.send_frames(0, 3)
    peer.wait_for(lambda: any(f.step == 2 for f in peer.frames))
    engine.server.disconnect()
    runner.join(20)
    engine.server.cleanup()
    assert result == [0]
    assert peer.hellos[0].client == "imd-bridge" and peer.hellos[0].session == "imd"


@pytest.mark.parametrize(
    ("argv", "code", "message"),
    [
        (["--connect", "localhost", "--topology", PDB_multiframe], 2, "HOST:PORT"),
        (["--connect", "localhost:8888", "--topology", "/nope.pdb"], 2, "no such file"),
        (["--connect", "h:1", "--topology", PDB_multiframe, "--max-force", "0"], 2, "positive"),
        (["--connect", "h:1", "--topology", PDB_multiframe, "--url", "x"], 2, "ws://HOST:PORT"),
        (["--connect", "h:1", "--topology", PDB_multiframe, "--units", "furlongs"], 2, "units"),
    ],
)
def test_cli_bad_input(
    argv: list[str], code: int, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert imd.main(argv) == code
    assert message in capsys.readouterr().err


def test_cli_engine_not_running(peer: SimPeer, capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    argv = ["--connect", f"127.0.0.1:{port}", "--topology", PDB_multiframe, "--url", peer.ws_url]
    assert imd.main([*argv, "--token", "secret", "--connect-timeout", "0.3"]) == 1
    assert "cannot connect to the MD engine" in capsys.readouterr().err

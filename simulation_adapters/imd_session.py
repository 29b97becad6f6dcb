"""A two-way IMD (v2 and v3) session with an MD engine: GROMACS, NAMD, LAMMPS.

The packet layouts, header types and body parsers come from `imdclient.IMDProtocol`; the socket,
the handshake and frame reading live here because the bridge must also *send* (forces, pause,
resume, transmission rate, kill) on the same socket while a reader thread waits for frames, must
tell a clean end of stream from a connection cut mid-frame, and must not install signal or atexit
handlers into its host process (which `imdclient.IMDClient` does).

Headers are big-endian; bodies, including the MDCOMM forces the receiver sends, use the engine's
byte order, which the handshake reveals. See imdclient's `protocol_v3.rst`.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import struct
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from imdclient.IMDProtocol import (
    IMDBOXPACKETLENGTH,
    IMDENERGYPACKETLENGTH,
    IMDHEADERSIZE,
    IMDTIMEPACKETLENGTH,
    IMDHeaderType,
    IMDSessionInfo,
    create_header_bytes,
    parse_energy_bytes,
    parse_imdv3_session_info,
)

log = logging.getLogger("scalesteer.imd")

SUPPORTED_VERSIONS = (2, 3)


class IMDError(Exception):
    """An IMD session that cannot continue, with a message naming the cause."""


class IMDHandshakeError(IMDError):
    """The peer did not complete an IMD v2/v3 handshake."""


class IMDAtomCountError(IMDError):
    """The engine sends a different number of atoms than the topology has."""


class IMDDisconnectedError(IMDError):
    """The engine closed the connection; `mid_frame` tells a cut frame from a clean end."""

    def __init__(self, message: str, mid_frame: bool) -> None:
        super().__init__(message)
        self.mid_frame = mid_frame


@dataclass
class EngineFrame:
    """One IMD frame, still in the engine's units (converted by the bridge)."""

    positions: npt.NDArray[np.float32]
    step: int | None = None
    time: float | None = None
    dt: float | None = None
    box: npt.NDArray[np.float32] | None = None
    energies: dict[str, float] | None = None
    extras: dict[str, npt.NDArray[np.float32]] = field(default_factory=dict)


class IMDSession:
    """One connection to an engine. `read_frame` runs on one thread; the command methods may be
    called from any other thread (sends are serialised by a lock)."""

    def __init__(self, sock: socket.socket, info: IMDSessionInfo, n_atoms: int, peer: str):
        self.sock = sock
        self.info = info
        self.n_atoms = n_atoms
        self.peer = peer
        self.version = int(info.version)
        self.endian = info.endianness  # '<' or '>'
        self.paused = False
        self.frames = 0
        self._send_lock = threading.Lock()
        self._closed = False
        self._in_frame = 0  # bytes read of the current frame
        self._last_energies: dict[str, float] | None = None

    # ------------------------------------------------------------------ connecting

    @classmethod
    def connect(
        cls,
        host: str,
        port: int,
        n_atoms: int,
        *,
        connect_timeout: float = 30.0,
        handshake_timeout: float = 30.0,
        wait_behavior: bool | None = None,
        cancel: threading.Event | None = None,
    ) -> IMDSession:
        """Connect (retrying while the engine is not listening yet), shake hands, send GO.

        `wait_behavior` (v3 only) asks the engine to wait for a receiver after we disconnect
        (True) or to carry on (False); None leaves the engine's setting alone.
        """
        peer = f"{host}:{port}"
        deadline = time.monotonic() + connect_timeout
        while True:
            try:
                sock = socket.create_connection((host, port), timeout=5.0)
                break
            except (ConnectionRefusedError, TimeoutError) as exc:
                if time.monotonic() >= deadline or (cancel is not None and cancel.is_set()):
                    raise IMDError(
                        f"cannot connect to the MD engine at {peer}: {exc} "
                        f"(is it running with IMD enabled on that port?)"
                    ) from None
                if cancel is not None:
                    cancel.wait(0.2)
                else:
                    time.sleep(0.2)
            except OSError as exc:
                raise IMDError(f"cannot connect to the MD engine at {peer}: {exc}") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            sock.settimeout(handshake_timeout)
            info = _handshake(sock, peer, handshake_timeout)
            sock.settimeout(None)
            session = cls(sock, info, n_atoms, peer)
            session._send(create_header_bytes(IMDHeaderType.IMD_GO, 0))
            if wait_behavior is not None and session.version >= 3:
                session._send(create_header_bytes(IMDHeaderType.IMD_WAIT, int(wait_behavior)))
        except BaseException:
            sock.close()
            raise
        log.info("IMD v%d session with %s (%s-endian)", session.version, peer, info.endianness)
        return session

    # ------------------------------------------------------------------ reading (one thread)

    def read_frame(self) -> EngineFrame:
        """Block until the next complete frame. Raises IMDDisconnectedError at the end of the
        stream, IMDAtomCountError on a mismatch, IMDError on a protocol violation."""
        self._in_frame = 0
        frame = self._read_v3() if self.version >= 3 else self._read_v2()
        self.frames += 1
        return frame

    def _read_v2(self) -> EngineFrame:
        # v2 engines send an optional energy block, then coordinates, in any frame
        energies = None
        while True:
            kind, length = self._header()
            if kind is IMDHeaderType.IMD_ENERGIES:
                energies = self._energies()
                self._last_energies = energies
            elif kind is IMDHeaderType.IMD_FCOORDS:
                pos = self._xyz(length, "coordinates")
                e = energies or self._last_energies
                step = int(e["step"]) if e is not None else None
                return EngineFrame(positions=pos, step=step, energies=e)
            else:
                raise IMDError(f"unexpected {kind.name} packet from a v2 engine")

    def _read_v3(self) -> EngineFrame:
        info = self.info
        frame = EngineFrame(positions=np.empty((0, 3), np.float32))
        if info.time:
            self._expect(IMDHeaderType.IMD_TIME)
            dt, t, step = struct.unpack(f"{self.endian}ddq", self._recv(IMDTIMEPACKETLENGTH))
            frame.dt, frame.time, frame.step = dt, t, step
        if info.energies:
            self._expect(IMDHeaderType.IMD_ENERGIES)
            frame.energies = self._energies()
            if frame.step is None:
                frame.step = int(frame.energies["step"])
        if info.box:
            self._expect(IMDHeaderType.IMD_BOX)
            raw = self._recv(IMDBOXPACKETLENGTH)
            frame.box = np.frombuffer(raw, dtype=f"{self.endian}f4").reshape(3, 3).astype("<f4")
        if info.positions:
            length = self._expect(IMDHeaderType.IMD_FCOORDS, check_length=False)
            frame.positions = self._xyz(length, "coordinates")
        if info.velocities:
            length = self._expect(IMDHeaderType.IMD_VELOCITIES, check_length=False)
            frame.extras["velocities"] = self._xyz(length, "velocities")
        if info.forces:
            length = self._expect(IMDHeaderType.IMD_FORCES, check_length=False)
            frame.extras["forces"] = self._xyz(length, "forces")
        return frame

    def _expect(self, kind: IMDHeaderType, check_length: bool = True) -> int:
        got, length = self._header()
        if got is not kind:
            raise IMDError(f"expected {kind.name} from the engine, got {got.name}")
        if check_length and length != 1:
            raise IMDError(f"{kind.name} packet announces {length} blocks, expected 1")
        return length

    def _header(self) -> tuple[IMDHeaderType, int]:
        raw = self._recv(IMDHEADERSIZE)
        value, length = struct.unpack("!ii", raw)
        try:
            kind = IMDHeaderType(value)
        except ValueError:
            raise IMDError(f"unknown IMD packet type {value} from the engine") from None
        if kind is IMDHeaderType.IMD_DISCONNECT:
            raise IMDDisconnectedError(f"the engine at {self.peer} ended the session", False)
        return kind, length

    def _energies(self) -> dict[str, float]:
        raw = self._recv(IMDENERGYPACKETLENGTH)
        return {str(k): float(v) for k, v in parse_energy_bytes(raw, self.endian).items()}

    def _xyz(self, length: int, what: str) -> npt.NDArray[np.float32]:
        if length != self.n_atoms:
            raise IMDAtomCountError(
                f"the engine sends {what} for {length} atoms but the topology has "
                f"{self.n_atoms}: give the topology of exactly the atoms the engine's IMD "
                f"group contains"
            )
        raw = self._recv(12 * length)
        return np.frombuffer(raw, dtype=f"{self.endian}f4").reshape(length, 3).astype("<f4")

    def _recv(self, n: int) -> bytes:
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        while got < n:
            try:
                k = self.sock.recv_into(view[got:])
            except OSError as exc:
                if self._closed:
                    raise IMDDisconnectedError("the session was closed", False) from None
                raise IMDDisconnectedError(
                    f"connection to the engine at {self.peer} failed: {exc}",
                    self._in_frame + got > 0,
                ) from None
            if k == 0:
                if self._closed:
                    raise IMDDisconnectedError("the session was closed", False)
                cut = self._in_frame + got > 0
                what = "in the middle of a frame" if cut else "between frames"
                raise IMDDisconnectedError(
                    f"the engine at {self.peer} closed the connection {what}", cut
                )
            got += k
        self._in_frame += n
        return bytes(buf)

    # ------------------------------------------------------------------ commands (any thread)

    def send_forces(self, indices: npt.ArrayLike, forces: npt.ArrayLike) -> None:
        """MDCOMM: apply these forces (engine units) to these atoms, replacing earlier ones."""
        idx = np.ascontiguousarray(indices, dtype=f"{self.endian}i4").reshape(-1)
        vec = np.ascontiguousarray(forces, dtype=f"{self.endian}f4").reshape(-1, 3)
        if idx.shape[0] != vec.shape[0]:
            raise ValueError("indices and forces differ in length")
        header = create_header_bytes(IMDHeaderType.IMD_MDCOMM, int(idx.shape[0]))
        self._send(header + idx.tobytes() + vec.tobytes())

    def pause(self) -> bool:
        """Pause the engine; False if it was already paused (v2 PAUSE toggles, so it is not
        sent twice)."""
        if self.paused and self.version < 3:
            return False
        was = self.paused
        self._send(create_header_bytes(IMDHeaderType.IMD_PAUSE, 0))
        self.paused = True
        return not was

    def resume(self) -> bool:
        """Resume the engine; False if it was not paused (v2 sends a second PAUSE, v3 RESUME)."""
        if not self.paused and self.version < 3:
            return False
        was = self.paused
        kind = IMDHeaderType.IMD_RESUME if self.version >= 3 else IMDHeaderType.IMD_PAUSE
        self._send(create_header_bytes(kind, 0))
        self.paused = False
        return was

    def set_rate(self, every: int) -> None:
        """TRATE: send a frame every `every` steps (< 1 restores the engine's default)."""
        self._send(create_header_bytes(IMDHeaderType.IMD_TRATE, int(every)))

    def kill(self) -> None:
        """Ask the engine to stop the simulation."""
        self._send(create_header_bytes(IMDHeaderType.IMD_KILL, 0))

    def close(self, disconnect: bool = True) -> None:
        """Say goodbye (DISCONNECT) if possible, then close; unblocks a waiting reader."""
        if self._closed:
            return
        if disconnect:
            with contextlib.suppress(IMDError):
                self._send(create_header_bytes(IMDHeaderType.IMD_DISCONNECT, 0), timeout=1.0)
        self._closed = True
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()

    def _send(self, data: bytes, timeout: float | None = 10.0) -> None:
        with self._send_lock:
            if self._closed:
                raise IMDDisconnectedError("the session was closed", False)
            try:
                # a send timeout guards against an engine that stopped reading; the socket's
                # own timeout would also apply to the reader thread, so select is used instead
                _sendall(self.sock, data, timeout)
            except OSError as exc:
                text = f"cannot send to the engine at {self.peer}: {exc}"
                raise IMDDisconnectedError(text, False) from None


def _sendall(sock: socket.socket, data: bytes, timeout: float | None) -> None:
    view = memoryview(data)
    deadline = None if timeout is None else time.monotonic() + timeout
    while view:
        remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
        _, writable, _ = select.select([], [sock], [], remaining)
        if not writable:
            raise TimeoutError("the engine does not read")
        try:
            sent = sock.send(view, socket.MSG_DONTWAIT)
        except BlockingIOError:
            continue
        view = view[sent:]


def _handshake(sock: socket.socket, peer: str, timeout: float) -> IMDSessionInfo:
    def recv(n: int, what: str) -> bytes:
        buf = b""
        while len(buf) < n:
            try:
                chunk = sock.recv(n - len(buf))
            except TimeoutError:
                raise IMDHandshakeError(
                    f"no IMD {what} from {peer} within {timeout:g} s "
                    f"(is that port an IMD port of a running engine?)"
                ) from None
            except OSError as exc:
                raise IMDHandshakeError(f"IMD handshake with {peer} failed: {exc}") from None
            if not chunk:
                raise IMDHandshakeError(f"{peer} closed the connection during the IMD handshake")
            buf += chunk
        return buf

    raw = recv(IMDHEADERSIZE, "handshake")
    kind = struct.unpack("!i", raw[:4])[0]
    if kind != IMDHeaderType.IMD_HANDSHAKE.value:
        raise IMDHandshakeError(f"{peer} did not start with an IMD handshake (packet type {kind})")
    big, little = struct.unpack(">i", raw[4:])[0], struct.unpack("<i", raw[4:])[0]
    if big in SUPPORTED_VERSIONS:
        version, endian = big, ">"
    elif little in SUPPORTED_VERSIONS:
        version, endian = little, "<"
    else:
        raise IMDHandshakeError(
            f"{peer} speaks IMD version {min(abs(big), abs(little))}; supported: 2 and 3"
        )
    if version == 2:
        return IMDSessionInfo(
            version=2,
            endianness=endian,
            wrapped_coords=False,
            energies=True,
            time=False,
            box=False,
            positions=True,
            velocities=False,
            forces=False,
        )
    head = recv(IMDHEADERSIZE, "session info")
    kind, length = struct.unpack("!ii", head)
    if kind != IMDHeaderType.IMD_SESSIONINFO.value:
        raise IMDHandshakeError(f"{peer} sent packet type {kind} instead of IMD v3 session info")
    if length != 7:
        raise IMDHandshakeError(f"{peer} sent IMD v3 session info of {length} bytes, expected 7")
    info: IMDSessionInfo = parse_imdv3_session_info(recv(7, "session info"), endian)
    if not info.positions:
        raise IMDHandshakeError(f"{peer} does not send coordinates in this IMD session")
    return info

"""Who is in a session: at most one simulation connection and any number of viewers/steerers."""

from __future__ import annotations

from dataclasses import dataclass, field

import protocol as p
from server.session.clients import Client


@dataclass
class Roster:
    sim: Client | None = None
    clients: dict[str, Client] = field(default_factory=dict)
    """Viewers and steerers by client id (the simulation is not among them)."""
    joined: dict[str, p.ClientInfo] = field(default_factory=dict)
    left: list[str] = field(default_factory=list)
    """Changes not yet broadcast (see `take_changes`)."""

    def note_join(self, client: Client) -> None:
        self.joined[client.client_id] = client.info()

    def note_leave(self, client: Client) -> None:
        if self.joined.pop(client.client_id, None) is None:
            self.left.append(client.client_id)

    def take_changes(self) -> p.State | None:
        """The roster changes since the last call as one `state` delta (None if nothing
        changed): a storm of joins costs one small message per client per interval, never
        the whole list per join."""
        if not self.joined and not self.left:
            return None
        delta = p.State(joined=list(self.joined.values()) or None, left=self.left or None)
        self.joined, self.left = {}, []
        return delta

    def add(self, client: Client) -> Client | None:
        """Take a client in; returns the simulation connection it replaces, if any."""
        if client.role != "simulation":
            self.clients[client.client_id] = client
            return None
        old = self.sim if self.sim is not client else None
        self.sim = client
        return old

    def remove(self, client: Client) -> bool:
        """Let a client go; True when it was the current simulation connection."""
        if client.role == "simulation":
            if self.sim is client:
                self.sim = None
                return True
            return False
        self.clients.pop(client.client_id, None)
        return False

    @property
    def empty(self) -> bool:
        return self.sim is None and not self.clients

    def infos(self) -> list[p.ClientInfo]:
        infos = [c.info() for c in self.clients.values()]
        if self.sim is not None:
            infos.insert(0, self.sim.info())
        return infos

    def broadcast(self, message: p.Message) -> None:
        """Send to every viewer and steerer (encoded once)."""
        if not self.clients:
            return
        data = p.encode(message)
        for client in list(self.clients.values()):
            client.send_encoded(data)

"""Prometheus metrics of one server instance (its own registry, so tests can run several)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest

_MS_BUCKETS = (1, 2, 4, 8, 16, 33, 66, 125, 250, 500, 1000, 4000)


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.frames_rendered = Counter("scalesteer_frames_rendered", "Renders done", registry=r)
        self.images_sent = Counter("scalesteer_images_sent", "Images sent to clients", registry=r)
        self.frames_dropped = Counter(
            "scalesteer_frames_dropped",
            "Images replaced before a slow client took them",
            registry=r,
        )
        self.frames_stale = Counter(
            "scalesteer_frames_stale",
            "Images whose encode finished after a newer image had gone to the client",
            registry=r,
        )
        self.sim_frames = Counter(
            "scalesteer_sim_frames", "Frames received from simulations", registry=r
        )
        self.errors = Counter("scalesteer_errors", "Error replies by code", ["code"], registry=r)
        self.render_ms = Histogram(
            "scalesteer_render_ms", "Render time (ms)", buckets=_MS_BUCKETS, registry=r
        )
        self.encode_ms = Histogram(
            "scalesteer_encode_ms", "Encode time (ms)", buckets=_MS_BUCKETS, registry=r
        )
        self.clients = Gauge("scalesteer_clients", "Connected clients", ["role"], registry=r)
        self.sessions = Gauge("scalesteer_sessions", "Live sessions", registry=r)
        self.batch_workers = Gauge(
            "scalesteer_batch_workers", "Ray render workers alive (0: jobs render here)", registry=r
        )
        self.jobs = Counter("scalesteer_jobs", "Batch jobs by final state", ["state"], registry=r)

    def text(self) -> bytes:
        return generate_latest(self.registry)

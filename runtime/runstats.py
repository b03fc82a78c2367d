"""Counters and timing for a dadiff-run session, and its one-paragraph summary."""

from __future__ import annotations

import time
from collections import deque

import numpy as np

KEPT_LATENCIES = 100_000  # percentiles over the most recent frames: a service running for days stays bounded


class RunStats:
    """Frames seen, lost and skipped; tracker latencies; end-to-end throughput."""

    def __init__(self) -> None:
        self.frames = 0
        self.lost = 0
        self.skipped = 0
        self.tracked = 0
        self.latency_sum = 0.0
        self.latencies: deque[float] = deque(maxlen=KEPT_LATENCIES)
        self.fps_recent: float | None = None
        self.begin()

    def begin(self) -> None:
        """Start the clock (at the first frame, so that model loading is not counted)."""
        self.started = time.perf_counter()
        self._window_start, self._window_frames = self.started, 0
        self._first_window_done = False

    def add(self, state: str, latency: float | None = None) -> None:
        """Count one processed frame (latency None for the init frame)."""
        self.frames += 1
        self.lost += state == "lost"
        if latency is not None:
            self.tracked += 1
            self.latency_sum += latency
            self.latencies.append(latency)
        self._window_frames += 1
        now = time.perf_counter()
        if now - self._window_start >= 1.0:
            self.fps_recent = self._window_frames / (now - self._window_start)
            self._window_start, self._window_frames = now, 0
            self._first_window_done = True
        elif not self._first_window_done and self._window_frames > 1:
            # until a whole second has passed, the rate so far (one frame alone would read as ~1e5 FPS)
            self.fps_recent = (self._window_frames - 1) / (now - self._window_start)

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def summary(self, interrupted: bool = False) -> str:
        elapsed = max(self.elapsed, 1e-9)
        line = f"{self.frames} frames, {self.lost} lost, {self.skipped} skipped"
        line += f"; mean {self.tracked / elapsed:.1f} FPS end to end"
        if self.tracked:
            p50, p95 = np.percentile(np.asarray(self.latencies) * 1000, [50, 95])
            line += f"; tracker {self.tracked / self.latency_sum:.1f} FPS, latency p50 {p50:.2f} ms, p95 {p95:.2f} ms"
        if interrupted:
            line += " (interrupted)"
        return line

"""Rendering in worker processes (`--render-workers N`): each worker builds its own Renderer
once and renders the snapshots it is sent; frames come back in submission order.

With workers <= 1 everything runs in this process, so callers need not care which.
"""

from __future__ import annotations

import multiprocessing as mp
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor

import numpy as np

from bid_sim.errors import BidError
from bid_sim.render.camera import CameraRig
from bid_sim.render.presets import preset
from bid_sim.render.renderer import Renderer
from bid_sim.snapshot import Snapshot
from bid_sim.town_map import load_town_map
from bid_sim.towns import Town, resolve_town

_WORKER: Renderer | None = None


def _init_worker(town: Town, rig: CameraRig, weather: str, seed: int) -> None:
    import cv2

    global _WORKER
    cv2.setNumThreads(1)  # one core per worker
    _WORKER = Renderer(load_town_map(town), rig, weather, seed)


def _render_in_worker(snapshot: Snapshot) -> np.ndarray:
    assert _WORKER is not None, "worker not initialised"
    return _WORKER.render(snapshot)


class RenderPool:
    """Renders snapshots of one town under one weather, in order, on N worker processes.

    ``submit`` queues a snapshot; ``ready`` yields the frames finished so far (in order),
    ``drain`` waits for all; ``map`` renders an iterable keeping at most ``ahead`` frames in
    flight. Use as a context manager, or call ``close``.
    """

    def __init__(self, town: Town | str, weather: str = "ClearNoon", workers: int = 1,
                 rig: CameraRig | None = None, seed: int = 0, ahead: int | None = None):
        if workers < 0:
            raise BidError(f"--render-workers must be >= 0, got {workers}")
        self.town = town if isinstance(town, Town) else resolve_town(town)
        self.weather = preset(weather).name
        self.rig = rig or CameraRig()
        self.workers = workers
        self.ahead = ahead or max(2, 3 * workers)
        self._pending: deque[Future | np.ndarray] = deque()
        self._local: Renderer | None = None
        self._pool: ProcessPoolExecutor | None = None
        if workers <= 1:
            self._local = Renderer(load_town_map(self.town), self.rig, self.weather, seed)
        else:
            # spawn, not fork: the parent may hold SUMO and torch threads.
            self._pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"),
                                             initializer=_init_worker,
                                             initargs=(self.town, self.rig, self.weather, seed))

    def submit(self, snapshot: Snapshot) -> None:
        if self._local is not None:
            self._pending.append(self._local.render(snapshot))
        else:
            assert self._pool is not None, "pool is closed"
            self._pending.append(self._pool.submit(_render_in_worker, snapshot))

    def __len__(self) -> int:
        """Frames submitted and not yet taken."""
        return len(self._pending)

    def ready(self) -> Iterator[np.ndarray]:
        """Frames finished so far, in submission order (stops at the first unfinished)."""
        while self._pending and (not isinstance(self._pending[0], Future) or self._pending[0].done()):
            yield self._take()

    def drain(self) -> Iterator[np.ndarray]:
        """All frames still pending, in order, waiting for each."""
        while self._pending:
            yield self._take()

    def _take(self) -> np.ndarray:
        item = self._pending.popleft()
        return item.result() if isinstance(item, Future) else item

    def map(self, snapshots: Iterable[Snapshot]) -> Iterator[np.ndarray]:
        """Frames of the snapshots, in order."""
        for snap in snapshots:
            self.submit(snap)
            if len(self._pending) >= self.ahead:
                yield self._take()
        yield from self.drain()

    def close(self) -> None:
        self._pending.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> RenderPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

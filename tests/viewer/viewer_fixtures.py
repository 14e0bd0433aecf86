"""A tiny scene workspace built here, with exactly known labels, colours and lifting outputs."""

from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occufly.camera import Camera, look_at
from occufly.fsutil import atomic_save_npy
from occufly.scene import Frame, Scene

# far from the origin on purpose: float16 would round these to whole metres or worse
ORIGIN = np.array([512_000.0, 5_400_000.0, 300.0])
COUNTS = {0: 40, 6: 600, 16: 300, 11: 5, 13: 55}  # unlabelled, grass, building, person, vehicle


@dataclass
class Tiny:
    ws: Path
    scene: Scene
    labels: np.ndarray
    confidence: np.ndarray
    origin: np.ndarray


def build_tiny(ws: Path, *, seed: int = 3) -> Tiny:
    rng = np.random.default_rng(seed)
    labels = np.concatenate([np.full(n, c, np.uint8) for c, n in COUNTS.items()])
    rng.shuffle(labels)
    n = len(labels)
    xyz = np.column_stack([rng.uniform(-20, 20, n), rng.uniform(-15, 15, n),
                           rng.uniform(0, 2, n)]).astype(np.float32)
    xyz[:, 0] += 1000.0  # local coordinates far from 0 as well: float16 step there is 0.5 m
    rgb = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    cam = Camera("PINHOLE", 400, 300, np.array([300.0, 300.0, 200.0, 150.0]))
    frames = [
        Frame(f"f{i}.jpg", cam, look_at(np.array([1000.0 + x, 0.0, 40.0]),
                                        np.array([1000.0 + x, 0.0, 0.0]), up=np.array([0.0, 1.0, 0.0])))
        for i, x in enumerate((-10.0, 10.0))
    ]
    scene = Scene(frames=frames, xyz=xyz, rgb=rgb, origin=ORIGIN)
    scene.save(ws)
    conf = np.linspace(0, 1, n, dtype=np.float32)
    origin = (np.arange(n) % 4).astype(np.uint8)
    atomic_save_npy(ws / "lifting" / "labels.npy", labels)
    atomic_save_npy(ws / "lifting" / "confidence.npy", conf)
    atomic_save_npy(ws / "lifting" / "origin.npy", origin)
    return Tiny(ws, Scene.load(ws), labels, conf, origin)


# ---- a viser client that records what it is sent (tests/viewer/test_point_lod.py, ...) ----
class FakeHandle:
    def __init__(self, log: list, name: str) -> None:
        self.log, self.name = log, name
        self.visible = True
        self.point_size = 0.0

    def remove(self) -> None:
        self.log.append(("remove", self.name, 0, None, None))


class FakeScene:
    """Records what a viser client would be sent, in order."""

    def __init__(self) -> None:
        self.log: list[tuple] = []
        self.lock = threading.Lock()

    def add_frame(self, name: str, **kw) -> FakeHandle:
        with self.lock:
            self.log.append(("frame", name, 0, None, kw.get("visible", True)))
        h = FakeHandle(self.log, name)
        h.visible = kw.get("visible", True)
        return h

    def add_point_cloud(self, name: str, *, points, colors, **kw) -> FakeHandle:
        with self.lock:
            self.log.append(("points", name, len(points), np.array(points), np.array(colors)))
        return FakeHandle(self.log, name)


    def add_batched_meshes_simple(self, name: str, *, batched_positions, **kw) -> FakeHandle:
        with self.lock:
            self.log.append(("boxes", name, len(batched_positions), kw.get("material"),
                             kw.get("visible", True)))
        h = FakeHandle(self.log, name)
        h.visible = kw.get("visible", True)
        return h


class FakeBox(FakeHandle):
    def __init__(self, log: list, name: str, value: bool) -> None:
        super().__init__(log, name)
        self.label, self.value = name, value

    def on_update(self, fn) -> None:
        pass


class FakeGui:
    def __init__(self, log: list) -> None:
        self.log = log

    def add_checkbox(self, label: str, initial_value: bool) -> FakeBox:
        return FakeBox(self.log, label, initial_value)


class FakeClient:
    def __init__(self) -> None:
        self.scene = FakeScene()
        self.notes: list[tuple[str, str]] = []
        self.gui = FakeGui(self.scene.log)

    @contextlib.contextmanager
    def atomic(self):
        """Logs ("atomic", "begin" / "end"): what viser sends in one message window."""
        self.scene.log.append(("atomic", "begin", 0, None, None))
        try:
            yield
        finally:
            self.scene.log.append(("atomic", "end", 0, None, None))

    def flush(self) -> None:
        pass

    def add_notification(self, title: str, body: str, **kw) -> None:
        self.notes.append((title, body))

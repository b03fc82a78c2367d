"""The per-frame path stays lean: one bound search call, no session rebuilt, no memory growth, a disk cache.

These tests guard structure, never time (speed is measured by `dadiff-bench`).
"""

from __future__ import annotations

import os
import tracemalloc
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest

from dadiff.runtime import OnnxBackend, Tracker
from dadiff.runtime import onnx_backend as backend_module
from dadiff.runtime.ort_cache import KEEP, cache_root, prune
from dadiff.runtime.runstats import KEPT_LATENCIES, RunStats
from runtime_models import write_corr_model
from runtime_scenes import moving_sequence


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_corr_model(tmp_path_factory.mktemp("lean") / "corr-test")


class CountingSession:
    """Wraps an InferenceSession and counts its calls."""

    def __init__(self, session: ort.InferenceSession) -> None:
        self.session = session
        self.calls = 0
        self.inputs: list[object] = []

    def run(self, *args, **kwargs):
        self.calls += 1
        return self.session.run(*args, **kwargs)

    def run_with_iobinding(self, *args, **kwargs):
        self.calls += 1
        return self.session.run_with_iobinding(*args, **kwargs)

    def __getattr__(self, name: str):
        return getattr(self.session, name)


def test_one_search_call_per_frame_and_one_template_call_per_init(model_dir: Path) -> None:
    tracker = Tracker.load(model_dir, threads=1)
    backend = tracker.backend
    search, template = CountingSession(backend._search), CountingSession(backend._template)
    backend._search, backend._template = search, template
    frames, boxes = moving_sequence(60)
    tracker.init(frames[0], boxes[0])
    for frame in frames[1:21]:
        tracker.update(frame)
    assert (template.calls, search.calls) == (1, 20)
    tracker.init(frames[5], boxes[5])
    tracker.update(frames[6])
    assert (template.calls, search.calls) == (2, 21)


def test_no_session_is_built_while_tracking(model_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    tracker = Tracker.load(model_dir, threads=1)
    built = []
    monkeypatch.setattr(backend_module.ort, "InferenceSession", lambda *a, **k: built.append(a))
    frames, boxes = moving_sequence(60)
    for start in (0, 6):  # re-initialising does not rebuild a session either
        tracker.init(frames[start], boxes[start])
        for frame in frames[start + 1:start + 6]:
            tracker.update(frame)
    assert built == []


def test_search_crop_is_written_into_the_bound_buffer(model_dir: Path) -> None:
    tracker = Tracker.load(model_dir, threads=1)
    backend = tracker.backend
    seen = []
    original = backend.search

    def spy(x, feeds):
        seen.append(x is backend.input_buffer)
        return original(x, feeds)

    backend.search = spy
    frames, boxes = moving_sequence(60)
    tracker.init(frames[0], boxes[0])
    results = [tracker.update(f) for f in frames[1:4]]
    assert seen == [True, True, True]
    assert all(r.score > 0.5 for r in results)


def test_bound_path_equals_plain_session_run(model_dir: Path) -> None:
    backend = OnnxBackend(model_dir, threads=1, cache=False)
    rng = np.random.default_rng(3)
    feeds = backend.template(rng.integers(0, 256, (1, 3, 127, 127)).astype(np.float32))
    plain = ort.InferenceSession(str(model_dir / "search.onnx"), providers=["CPUExecutionProvider"])
    for _ in range(3):
        x = rng.integers(0, 256, (1, 3, 255, 255)).astype(np.float32)
        cls, loc = backend.search(x, feeds)
        inputs = {"x": x} | {i.name: feeds[i.name] for i in plain.get_inputs() if i.name != "x"}
        ref_cls, ref_loc = plain.run(["cls", "loc"], inputs)
        np.testing.assert_array_equal(cls, ref_cls)
        np.testing.assert_array_equal(loc, ref_loc)
    other = backend.template(rng.integers(0, 256, (1, 3, 127, 127)).astype(np.float32))
    x = rng.integers(0, 256, (1, 3, 255, 255)).astype(np.float32)
    first, _ = backend.search(x, feeds)  # switching targets rebinds the kernels
    second, _ = backend.search(x, other)
    assert not np.array_equal(first, second)


def test_tracking_does_not_grow_python_memory(model_dir: Path) -> None:
    tracker = Tracker.load(model_dir, threads=1)
    frames, boxes = moving_sequence(80)
    tracker.init(frames[0], boxes[0])
    for frame in frames[1:40]:
        tracker.update(frame)
    tracemalloc.start()
    try:
        for frame in frames[40:]:  # the still check's window (31 rings, about 0.5 MB) now held in traced arrays
            tracker.update(frame)
        before = tracemalloc.take_snapshot()
        for _ in range(5):
            for frame in frames[40:]:
                tracker.update(frame)
        after = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
    growth = sum(s.size_diff for s in after.compare_to(before, "filename"))
    assert growth < 64 * 1024, f"python allocations grew by {growth} bytes over 200 frames"


def test_run_statistics_keep_a_bounded_window() -> None:
    stats = RunStats()
    for i in range(KEPT_LATENCIES + 10):
        stats.add("tracking", 0.01 + (i % 3) * 0.001)
    assert len(stats.latencies) == KEPT_LATENCIES
    assert stats.tracked == KEPT_LATENCIES + 10
    assert "p50 11.00 ms" in stats.summary()


def test_threads_default_to_physical_cores() -> None:
    cores = backend_module.physical_cores()
    assert 1 <= cores <= (os.cpu_count() or 1)
    assert backend_module.session_options().intra_op_num_threads == cores


def test_pool_threads_spin_within_a_call_only() -> None:
    """Spinning between kernels of one call, stopped when it returns: an idle tracker burns no CPU."""
    options = backend_module.session_options()
    assert options.get_session_config_entry("session.intra_op.allow_spinning") == "1"
    assert options.get_session_config_entry("session.force_spinning_stop") == "1"


def test_optimised_graphs_are_cached_and_reused(model_dir: Path, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("DADIFF_CACHE_DIR", str(tmp_path / "cache"))
    first = OnnxBackend(model_dir, threads=1)
    cached = sorted(p.name for p in (tmp_path / "cache").glob("*.onnx"))
    assert [name.split("-")[0] for name in cached] == ["search", "template"]
    opened = []
    real = ort.InferenceSession

    def recording(path, *args, **kwargs):
        opened.append(Path(path).parent.name)
        return real(path, *args, **kwargs)

    monkeypatch.setattr(backend_module.ort, "InferenceSession", recording)
    second = OnnxBackend(model_dir, threads=1)
    assert opened == ["cache", "cache"]
    assert second.meta == first.meta  # the metadata survives onnxruntime's rewrite
    z = np.full((1, 3, 127, 127), 90, np.float32)
    x = np.full((1, 3, 255, 255), 60, np.float32)
    a, b = first.search(x, first.template(z)), second.search(x, second.template(z))
    np.testing.assert_array_equal(a[0], b[0])


def test_damaged_cache_entry_is_rebuilt(model_dir: Path, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("DADIFF_CACHE_DIR", str(tmp_path))
    OnnxBackend(model_dir, threads=1)
    for entry in tmp_path.glob("*.onnx"):
        entry.write_bytes(b"not a graph")
    backend = OnnxBackend(model_dir, threads=1)
    assert backend.search(np.zeros((1, 3, 255, 255), np.float32), backend.template(np.zeros((1, 3, 127, 127),
                          np.float32)))[0].shape == (1, 2, 25, 25)
    assert all(e.stat().st_size > 100 for e in tmp_path.glob("*.onnx"))


def test_cache_off_or_unwritable_writes_nothing(model_dir: Path, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("DADIFF_CACHE_DIR", "off")
    assert cache_root() is None
    OnnxBackend(model_dir, threads=1)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    monkeypatch.setenv("DADIFF_CACHE_DIR", str(locked))
    try:
        OnnxBackend(model_dir, threads=1)
        assert os.geteuid() == 0 or list(locked.iterdir()) == []
    finally:
        locked.chmod(0o700)


def test_no_home_means_no_cache(monkeypatch) -> None:
    monkeypatch.delenv("DADIFF_CACHE_DIR", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)

    def no_home() -> Path:
        raise RuntimeError("Could not determine home directory.")

    monkeypatch.setattr(Path, "home", staticmethod(no_home))
    assert cache_root() is None


def test_cache_keeps_only_the_most_recent_graphs(tmp_path: Path) -> None:
    for i in range(KEEP + 3):
        entry = tmp_path / f"m{i}.onnx"
        entry.write_bytes(b"x")
        os.utime(entry, (i, i))
    prune(tmp_path)
    assert sorted(p.name for p in tmp_path.glob("*.onnx")) == sorted(f"m{i}.onnx" for i in range(3, KEEP + 3))


def test_prune_skips_an_entry_another_process_removed_meanwhile(tmp_path: Path) -> None:
    """Two trackers starting at once prune one cache folder: an entry listed but gone before its stat (here a
    dangling link) is skipped instead of failing the load ("No such file or directory", seen with two
    `dadiff-eval run` at once)."""
    (tmp_path / "gone.onnx").symlink_to(tmp_path / "removed-by-the-other-process.onnx")
    for i in range(KEEP + 1):
        entry = tmp_path / f"m{i}.onnx"
        entry.write_bytes(b"x")
        os.utime(entry, (i + 1, i + 1))
    prune(tmp_path)
    assert not (tmp_path / "m0.onnx").exists() and (tmp_path / f"m{KEEP}.onnx").exists()


def test_recent_fps_is_right_before_the_first_second(monkeypatch) -> None:
    """A clip shorter than a second: the overlay's FPS is the rate so far, not one frame over microseconds
    (it read 105219 FPS on a 120-frame clip)."""
    from dadiff.runtime import runstats

    clock = iter([0.0, 1e-5, *(0.01 * k for k in range(1, 10))])
    monkeypatch.setattr(runstats.time, "perf_counter", lambda: next(clock))
    stats = runstats.RunStats()
    stats.add("init")
    assert stats.fps_recent is None
    for _ in range(9):
        stats.add("tracking", 0.01)
    assert stats.fps_recent == pytest.approx(100.0)

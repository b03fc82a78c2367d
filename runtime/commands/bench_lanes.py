"""Where a frame's time goes: per-stage latency, throughput and memory of the tracker on a night video.

The stages follow a frame through the onboard pipeline: video decode, search crop, the ONNX search call,
box decoding and state (post), and packing the MAVLink CAMERA_TRACKING_IMAGE_STATUS (275) the drone sends;
the template branch runs once per target and is timed per init. The video is generated (runtime/datamaking/scenes.py,
test photos), written with the codec dadiff-run reads, and looped with a re-init for long runs.
"""

from __future__ import annotations

import resource
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..backend import RecordingBackend
from ..datamaking.scenes import make_sequence
from ..evaluation.evaluate import BoxTracker, protocol_box
from ..outputs import open_mp4
from ..tracker import Tracker, TrackResult

STAGES = ("decode", "motion", "crop", "search", "post", "encode", "tracker", "frame")
RSS_EVERY = 500  # frames between resident-memory samples


@dataclass(frozen=True)
class NightVideo:
    path: Path
    name: str
    first_box: tuple[float, float, float, float]
    frames: int


def write_night_video(folder: Path, seed: int = 0, frames: int = 300) -> NightVideo:
    """Render generated night sequence `seed` (test photos) to `folder`/night-<seed>.mp4."""
    sequence = make_sequence(seed, split="test", frames=frames)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"night-{seed}.mp4"
    height, width = sequence.night[0].shape[:2]
    writer = open_mp4(path, (width, height))
    for frame in sequence.night:
        writer.write(frame)
    writer.close()
    return NightVideo(path, sequence.name, protocol_box(sequence.boxes[0]), frames)


def rss_bytes() -> int:
    """Resident memory of this process now (Linux /proc; peak RSS elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize()
    except OSError:
        return peak_rss_bytes()


def peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


class StatusEncoder:
    """Packs the 275 message for a result exactly as the drone's camera component does."""

    def __init__(self) -> None:
        from dadiff.drone.camera import tracking_status  # the drone side is torch-free too
        from dadiff.drone.mav import mavlink
        from dadiff.drone.tracking import Snapshot

        self._status, self._snapshot = tracking_status, Snapshot
        self._mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=mavlink.MAV_COMP_ID_CAMERA)

    def __call__(self, result: TrackResult, frame_size: tuple[int, int], index: int) -> bytes:
        snapshot = self._snapshot(
            seq=index, target_id=1, state=result.state, box=result.box, score=result.score,
            frame_size=frame_size, frame_index=index,
        )
        return self._status(snapshot).pack(self._mav)


def latency_ms(seconds: Sequence[float] | np.ndarray) -> dict[str, float]:
    """Median and 95th percentile of durations in seconds, in milliseconds."""
    ms = np.asarray(seconds) * 1000
    return {"p50": float(np.median(ms)), "p95": float(np.percentile(ms, 95))}


@dataclass
class BenchRun:
    """Raw per-frame timings (seconds) after warm-up, init timings, and memory samples.

    The timings go into arrays allocated and touched before the first frame, so that the benchmark's own
    bookkeeping does not show up as memory growth of the tracker. `seconds` is the time spent in this
    tracker's own frames, so the frame rate is its own even when other trackers ran in between.
    """

    frames: int
    seconds: float
    stages: dict[str, np.ndarray] = field(default_factory=dict)
    template: list[float] = field(default_factory=list)
    rss: list[tuple[int, int]] = field(default_factory=list)  # (frame, bytes)
    peak_rss: int = 0

    def summary(self) -> dict:
        """Medians and p95 in ms per stage, end-to-end FPS, the share outside the ONNX call, memory."""
        out: dict = {"frames": self.frames, "seconds": self.seconds, "fps": self.frames / self.seconds}
        for name, values in {**self.stages, "template": self.template}.items():
            out[name] = latency_ms(values) if len(values) else None
        if "search" in self.stages:
            tracker, frame, search = (np.asarray(self.stages[k]) for k in ("tracker", "frame", "search"))
            out["outside_onnx_tracker"] = float(np.median((tracker - search) / tracker))
            out["outside_onnx_frame"] = float(np.median((frame - search) / frame))
        if self.rss:
            first, last = self.rss[0][1], self.rss[-1][1]
            out["rss_mb"] = {"first": first / 2**20, "last": last / 2**20, "growth": (last - first) / 2**20,
                             "peak": self.peak_rss / 2**20, "samples": [(i, b / 2**20) for i, b in self.rss]}
        return out


def _open(video: NightVideo) -> cv2.VideoCapture:
    capture = cv2.VideoCapture(str(video.path))
    if not capture.isOpened():
        raise OSError(f"{video.path}: cannot open video")
    return capture


def _init(tracker: Tracker | BoxTracker, capture: cv2.VideoCapture, video: NightVideo) -> float:
    ok, frame = capture.read()
    if not ok:
        raise OSError(f"{video.path}: cannot read the first frame")
    start = time.perf_counter()
    tracker.init(frame, video.first_box)
    return time.perf_counter() - start


class BenchLane:
    """One tracker's pass over the looped clip, run a block of frames at a time.

    A dadiff `Tracker` gets every stage (crop, search, post from its own latency record, plus the MAVLink
    275 packing); a baseline `BoxTracker` (OpenCV's TrackerNano) only video decode, update and frame.
    `cv2_threads`, when set, is OpenCV's thread count during this lane's frames.
    """

    def __init__(self, tracker: Tracker | BoxTracker, video: NightVideo, frames: int, template_runs: int = 10,
                 cv2_threads: int | None = None) -> None:
        self.tracker, self.video, self.frames, self.cv2_threads = tracker, video, frames, cv2_threads
        full = isinstance(tracker, Tracker)
        self.encode = StatusEncoder() if full else None
        stages = STAGES if full else ("decode", "tracker", "frame")
        self.capture = _open(video)
        with self.opencv_threads():
            template = []
            for _ in range(template_runs):  # the template branch on its own, then the real init
                self.capture.set(cv2.CAP_PROP_POS_FRAMES, 0)
                template.append(_init(tracker, self.capture, video))
        self.run = BenchRun(frames=frames, seconds=0.0, template=template[1:],
                            stages={s: np.full(frames, np.nan) for s in stages})
        self.done = 0

    @contextmanager
    def opencv_threads(self) -> Iterator[None]:
        """OpenCV's thread count set to this lane's (when it has one) for the block, then restored."""
        before = cv2.getNumThreads()
        if self.cv2_threads is not None:
            cv2.setNumThreads(self.cv2_threads)
        try:
            yield
        finally:
            cv2.setNumThreads(before)

    def _frame(self) -> tuple[np.ndarray, float]:
        """The next frame and the moment its decode started; the clip restarts with a re-init at its end."""
        t0 = time.perf_counter()
        ok, frame = self.capture.read()
        if not ok:
            self.capture.release()
            self.capture = _open(self.video)
            self.run.template.append(_init(self.tracker, self.capture, self.video))
            t0 = time.perf_counter()
            ok, frame = self.capture.read()
        return frame, t0

    def warm_up(self, count: int) -> None:
        """Untimed frames: kernels chosen, caches and buffers filled."""
        with self.opencv_threads():
            for _ in range(count):
                frame, _ = self._frame()
                result = self.tracker.update(frame)
                if self.encode is not None:
                    self.encode(result, (frame.shape[1], frame.shape[0]), -1)

    def advance(self, count: int, progress: Callable[[int], None] | None = None) -> None:
        """Time the next `count` frames (fewer at the end of the run)."""
        run = self.run
        with self.opencv_threads():
            started = time.perf_counter()
            for i in range(self.done, min(self.done + count, self.frames)):
                if i == 0:
                    run.rss.append((0, rss_bytes()))
                frame, t0 = self._frame()
                t1 = time.perf_counter()
                result = self.tracker.update(frame)
                t2 = time.perf_counter()
                if self.encode is None:
                    timed = {"decode": t1 - t0, "tracker": t2 - t1, "frame": t2 - t0}
                else:
                    self.encode(result, (frame.shape[1], frame.shape[0]), i)
                    t3 = time.perf_counter()
                    lat = result.latency
                    timed = {"decode": t1 - t0, "motion": lat["motion"], "crop": lat["crop"], "search": lat["search"],
                             "post": lat["post"], "encode": t3 - t2, "tracker": t2 - t1, "frame": t3 - t0}
                for name, value in timed.items():
                    run.stages[name][i] = value
                if (i + 1) % RSS_EVERY == 0 or i == self.frames - 1:
                    run.rss.append((i + 1, rss_bytes()))
                self.done = i + 1
                if progress is not None:
                    progress(i + 1)
            run.seconds += time.perf_counter() - started

    def finish(self) -> BenchRun:
        # Linux updates ru_maxrss from per-thread counters it syncs now and then, so /proc can read a little
        # above it: the peak is never below a sample taken
        self.run.peak_rss = max([peak_rss_bytes(), *(b for _, b in self.run.rss)])
        return self.run


def run_lanes(lanes: Sequence[BenchLane], warmup: int = 20, block: int = 50,
              progress: Callable[[int], None] | None = None) -> list[BenchRun]:
    """Run the lanes in turns of `block` frames each (0: each lane to its end, one after another).

    Turns keep a slow minute of a shared machine from landing on one tracker only: their ratio is then
    measured over the same stretch of time. Every lane warms up just before its first timed frame.
    """
    try:
        if block <= 0:
            for lane in lanes:
                lane.warm_up(warmup)
                lane.advance(lane.frames, progress)
        else:
            for lane in lanes:
                lane.warm_up(warmup)
            while any(lane.done < lane.frames for lane in lanes):
                for lane in lanes:
                    lane.advance(block, progress)
        return [lane.finish() for lane in lanes]
    finally:
        for lane in lanes:
            lane.capture.release()


def search_crops(tracker: Tracker, video: NightVideo, count: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """(template inputs, xs): the template crop `z` (and the target's `roi` for a model that takes it) and the
    first `count` search crops the tracker makes on the video."""
    recorder = RecordingBackend(tracker.backend, count)
    recording = Tracker(recorder, overrides=asdict(tracker.params))  # same settings, recorded backend
    capture = _open(video)
    try:
        _init(recording, capture, video)
        while not recorder.full:
            ok, frame = capture.read()
            if not ok:
                break
            recording.update(frame)
    finally:
        capture.release()
    template = {"z": recorder.templates[0]}
    if recorder.rois[0] is not None:
        template["roi"] = recorder.rois[0]
    return template, np.concatenate([feed[recorder.image_name] for feed in recorder.recorded])


def time_search(tracker: Tracker, template: dict[str, np.ndarray], xs: np.ndarray, repeats: int = 3) -> list[float]:
    """Seconds per search-graph call on exactly these crops (the ORT side of the torch comparison)."""
    backend = tracker.backend
    feeds = backend.template(**template)
    backend.search(xs[:1], feeds)
    times = []
    for _ in range(repeats):
        for x in xs:
            start = time.perf_counter()
            backend.search(x[None], feeds)
            times.append(time.perf_counter() - start)
    return times

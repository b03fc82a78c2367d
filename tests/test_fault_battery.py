"""Fault and fuzz battery (issue 13), bounded in time: its figures go into docs/reliability.md.

1. MAVLink: random and mutated datagrams and commands against the running service; it must keep
   heartbeating and answer a good command afterwards.
2. Files: corrupted videos, frames, model files, checkpoints and configs against every command, each in a
   child process under a time limit: no traceback, no hang, one `<command>: error:` line and exit 2 (or
   exit 0 where a damaged video still decodes).
2b. A new user's faults (issue 55): FIFOs and devices where a file belongs, damaged NanoTrack weights,
   MAVLink addresses that cannot work, inputs the user may not read; the same verdicts.
3. Soak: the service over >= 10 000 frames while the camera and the link drop and come back every ~1 s:
   no row lost, flat memory, reconnect times measured.
4. Endings (issue 55): every output onto a disk that fills (RLIMIT_FSIZE, so no mount is needed) is reported
   with one line naming it and exit != 0, and left whole up to its last row or removed; SIGINT, SIGTERM and
   SIGHUP mid-run finalise the MP4; and the same signals while a command still imports are one line, exit 130.

Reproduce the figures: `DADIFF_BATTERY_REPORT=battery.json pytest -q tests/test_fault_battery.py`
(they are printed with `-s` as well). Seeds are fixed: every run attacks with the same inputs.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import random
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from conftest import hangup_as_in_a_session
from dadiff.drone.link import LinkSettings
from dadiff.drone.mav import mavlink
from dadiff.drone.service import Service, ServiceSettings
from dadiff.runtime.outputs import TrackLog
from dadiff.runtime.sources import Frame
from drone_peers import Autopilot, FakeTracker, Rig, free_port, wait_until

HERE = Path(__file__).resolve().parent
FIGURES: dict[str, Any] = {}


@pytest.fixture(scope="module", autouse=True)
def report() -> Iterator[None]:
    yield
    text = json.dumps(FIGURES, indent=1, sort_keys=True)
    print(f"\nfault battery figures:\n{text}")
    target = os.environ.get("DADIFF_BATTERY_REPORT")
    if target:
        Path(target).write_text(text + "\n")


def mutate(data: bytes, rng: random.Random) -> bytes:
    """One random damage: truncation, flipped bytes, a zeroed or random span, inserted junk, or noise."""
    if not data:
        return bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64)))
    kind = rng.randrange(6)
    buf = bytearray(data)
    if kind == 0:
        return bytes(buf[: rng.randrange(len(buf))])
    if kind == 1:
        for _ in range(rng.randrange(1, 9)):
            buf[rng.randrange(len(buf))] ^= 1 << rng.randrange(8)
        return bytes(buf)
    if kind == 2:
        start = rng.randrange(len(buf))
        end = min(len(buf), start + rng.randrange(1, 64))
        buf[start:end] = bytes(end - start) if rng.random() < 0.5 else rng.randbytes(end - start)
        return bytes(buf)
    if kind == 3:
        at = rng.randrange(len(buf) + 1)
        return bytes(buf[:at]) + rng.randbytes(rng.randrange(1, 32)) + bytes(buf[at:])
    if kind == 4:
        return rng.randbytes(len(buf))
    return bytes(buf[rng.randrange(len(buf)):]) + bytes(buf[: rng.randrange(len(buf))])


# ------------------------------------------------------------------------------------------ 1. MAVLink

N_DATAGRAMS = 3000
N_COMMANDS = 600


def _good_frames(rng: random.Random) -> list[bytes]:
    """Packed frames a ground station might send, to be mutated."""
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    msgs = [
        mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3),
        mavlink.MAVLink_command_long_message(1, 100, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 259, 0, 0, 0, 0, 0, 0),
        mavlink.MAVLink_command_long_message(1, 100, mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0, 0.4, 0.4, 0.6, 0.6,
                                             0, 0, 0),
        mavlink.MAVLink_command_int_message(1, 100, 0, mavlink.MAV_CMD_CAMERA_TRACK_POINT, 0, 0, 0.5, 0.5, 0.1, 0,
                                            0, 0, 0),
        mavlink.MAVLink_command_long_message(1, 100, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 275, 50000, 0, 0, 0,
                                             0, 0),
    ]
    return [m.pack(mav) for m in msgs]


def _random_command(rng: random.Random, mav: Any) -> bytes:
    """A well-formed command with a random id (often ours) and random, often absurd, parameters."""
    ours = (mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE, mavlink.MAV_CMD_CAMERA_TRACK_POINT,
            mavlink.MAV_CMD_CAMERA_STOP_TRACKING, mavlink.MAV_CMD_REQUEST_MESSAGE,
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 521, 522, 525, 527)
    command = rng.choice(ours) if rng.random() < 0.7 else rng.randrange(65536)
    pool = (float("nan"), float("inf"), -float("inf"), 0.0, -1.0, 1e38, -1e38, 0.5, 1.0, 2.0, 275.0, 1e-30)
    params = [rng.choice(pool) if rng.random() < 0.7 else rng.uniform(-2, 2) for _ in range(7)]
    target = (rng.choice((0, 1, 1, 1, 7)), rng.choice((0, 100, 100, 100, 101)))
    source = rng.choice((255, 245, 1, 42))
    mav.srcSystem = source
    if rng.random() < 0.5:
        msg = mavlink.MAVLink_command_long_message(*target, command, rng.randrange(256), *params)
    else:
        ints = [int(max(-2**31, min(2**31 - 1, p))) if np.isfinite(p) else 0 for p in params[4:6]]
        msg = mavlink.MAVLink_command_int_message(*target, 0, command, 0, 0, *params[:4], *ints, params[6])
    return msg.pack(mav)


def _datagrams(rng: random.Random) -> Iterator[bytes]:
    good = _good_frames(rng)
    for i in range(N_DATAGRAMS):
        kind = i % 4
        if kind == 0:
            yield rng.randbytes(rng.randrange(1, 300))
        elif kind == 1:
            yield mutate(rng.choice(good), rng)
        elif kind == 2:  # several frames, some damaged, glued into one datagram
            yield b"".join(mutate(f, rng) if rng.random() < 0.5 else f for f in rng.sample(good, 3))
        else:
            yield rng.choice((b"\xfd", b"\xfe", b"\xfd\xff", b"")) + rng.randbytes(rng.randrange(0, 40))


def _ack_on(sock: socket.socket, command: int, timeout: float) -> Any | None:
    """The COMMAND_ACK for `command` among the datagrams that come back to `sock`."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        sock.settimeout(max(0.01, end - time.monotonic()))
        try:
            data = sock.recv(65535)
        except TimeoutError:
            return None
        for msg in parser.parse_buffer(data) or []:
            if msg.get_type() == "COMMAND_ACK" and msg.command == command:
                return msg
    return None


def test_mavlink_fuzz_leaves_the_service_answering(caplog) -> None:
    caplog.set_level(logging.INFO, logger="dadiff.drone")
    rng = random.Random(13)
    with Rig(source={"fps": 30.0}) as rig:
        assert rig.connected()
        mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        started = time.monotonic()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            for i, data in enumerate(_datagrams(rng)):
                sock.sendto(data, ("127.0.0.1", rig.port))
                if i % 200 == 0:
                    time.sleep(0.01)  # a flood, not a socket-buffer overflow test
            for i in range(N_COMMANDS):
                sock.sendto(_random_command(rng, mav), ("127.0.0.1", rig.port))
                if i % 100 == 0:
                    time.sleep(0.01)
            flood_s = time.monotonic() - started
            after = time.monotonic()
            # a good command behind junk that holds a frame start (0xFD) is still answered
            mav.srcSystem = 255
            request = mavlink.MAVLink_command_long_message(1, 100, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 259, 0, 0,
                                                           0, 0, 0, 0).pack(mav)
            sock.sendto(b"\xfd\x20\x00\x00junk" + request, ("127.0.0.1", rig.port))
            junk_ack = _ack_on(sock, mavlink.MAV_CMD_REQUEST_MESSAGE, 3.0)  # udpin answers the last sender
        beats = rig.gcs.wait_for("HEARTBEAT", 3, after, where=lambda m: m.get_srcComponent() == 100)
        reply = rig.gcs.call(mavlink.MAV_CMD_REQUEST_MESSAGE, 259)
        assert rig.service.started.is_set() and rig.rc is None  # still running
        assert beats is not None and reply is not None and reply.result == mavlink.MAV_RESULT_ACCEPTED
        assert junk_ack is not None
        bad = rig.service.link.bad
    lines = [r for r in caplog.records if r.name.startswith("dadiff.drone")]
    FIGURES["mavlink"] = {"datagrams": N_DATAGRAMS, "commands": N_COMMANDS, "flood_seconds": round(flood_s, 2),
                          "bad_packets_counted": bad, "log_lines": len(lines), "heartbeat_after": True,
                          "good_command_answered": True, "junk_prefixed_command_answered": True}
    assert len(lines) < 100  # throttled: was one line per rejected command (1262 in a flood)


# ---------------------------------------------------------------------------------------------- 2. files

N_VIDEOS, N_FOLDERS, N_MODELS, N_RUN_CONFIGS, N_HP, N_BENCH_MODELS = 24, 12, 24, 24, 24, 8
N_EVAL_MODELS, N_EVAL_DATASETS, N_EVAL_RESULTS = 8, 8, 8
N_DETECTIONS, N_DETECTORS = 8, 6
N_CHECKPOINTS, N_EXPORT_MODELS, N_TRAIN_CONFIGS = 24, 6, 24
PROGS = {"dadiff.runtime.commands.run": "dadiff-run", "dadiff.runtime.commands.eval": "dadiff-eval",
         "dadiff.export.cli": "dadiff-export", "dadiff.export.train_cli": "dadiff-train",
         "dadiff.runtime.commands.bench": "dadiff-bench"}
BOX = "40,40,20,15"


def _frames(n: int = 20) -> list[np.ndarray]:
    out = []
    for i in range(n):
        image = np.full((120, 160, 3), 30, np.uint8)
        image[40:55, 40 + i:60 + i] = 220
        out.append(image)
    return out


def _video(path: Path, fourcc: str) -> bytes:
    import cv2

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 25.0, (160, 120))
    for image in _frames():
        writer.write(image)
    writer.release()
    return path.read_bytes()


def _sequence(folder: Path, frames: list[np.ndarray], ext: str = ".jpg") -> Path:
    import cv2

    (folder / "img").mkdir(parents=True)
    for k, image in enumerate(frames):
        cv2.imwrite(str(folder / "img" / f"{k + 1:04d}{ext}"), image)
    (folder / "groundtruth_rect.txt").write_text("".join(f"{40 + k},40,20,15\n" for k in range(len(frames))))
    return folder


def _damaged_model(folder: Path, base: Path, rng: random.Random, i: int) -> Path:
    """A copy of `base` with one graph's bytes damaged, or (every third) one metadata key set to garbage."""
    from runtime_models import write_corr_model

    if i % 3 == 2:
        key = rng.choice(("dadiff_format", "exemplar_size", "instance_size", "stride", "score_size", "lr",
                          "point_origin", "hp_presets", "channel_order", "pixel_range", "lost_frames"))
        return write_corr_model(folder, meta={key: rng.choice(("", "nan", "-1", "0", "1e309", "x", "{", "[]"))})
    folder.mkdir(parents=True)
    for name in ("template.onnx", "search.onnx"):
        data = (base / name).read_bytes()
        (folder / name).write_bytes(mutate(data, rng) if name == rng.choice(("template.onnx", "search.onnx"))
                                    else data)
    return folder


def _run_config(rng: random.Random) -> bytes:
    """A dadiff-run config that must be refused (garbage values, unknown keys, broken TOML, not text)."""
    kind = rng.randrange(5)
    if kind == 0:
        return rng.randbytes(rng.randrange(1, 200))
    if kind == 1:
        return b'video = "x\nmodel = [1,'
    if kind == 2:
        return f"{rng.choice(('vidoe', 'frobnicate', 'max_speed_x', 'help', 'config'))} = 1\n".encode()
    key = rng.choice(("init", "threads", "max-frames", "hp", "sysid", "component", "allow-sysid", "tracking-rate",
                      "follow", "max-speed", "log-level", "link-timeout", "mavlink", "follow-rate", "gimbal-rate"))
    value = rng.choice(('"x"', "-1", "0", "1e308", '"nan"', "[1, 2]", "{a = 1}", '""', '"' + "9" * 300 + '"'))
    return f'video = "/nonexistent/flight.mp4"\n{key} = {value}\n'.encode()


def _hp(rng: random.Random) -> str:
    """An --hp override list with extreme, odd or wrong values (the tracker must refuse or survive them)."""
    keys = ("lr", "penalty_k", "window_influence", "uncertain_score", "found_score", "lost_score", "lost_frames",
            "search_growth", "search_growth_max", "track_score", "score_smoothing", "max_scale_step",
            "max_scale_change", "max_aspect_change", "max_frame_cover", "motion_compensation", "still_frames",
            "still_travel", "swap_frames", "swap_distance", "colour_prior", "no_such_key")
    values = ("1e308", "-1e308", "nan", "inf", "0", "1", "-0", "1e-308", "2", "0.5", "x", "3.0", "1000000")
    return ",".join(f"{rng.choice(keys)}={rng.choice(values)}" for _ in range(rng.randrange(1, 4)))


def _runtime_cases(root: Path, rng: random.Random) -> list[dict[str, Any]]:
    from runtime_models import write_corr_model

    model = write_corr_model(root / "model")
    bases = {".mp4": _video(root / "base.mp4", "mp4v"), ".avi": _video(root / "base.avi", "MJPG")}
    cases: list[dict[str, Any]] = []

    def add(kind: str, module: str, argv: list[str], strict: bool) -> None:
        cases.append({"id": f"{kind}-{len(cases)}", "kind": kind, "module": module, "argv": argv, "strict": strict,
                      "limit": 60})

    run = "dadiff.runtime.commands.run"
    for i in range(N_VIDEOS):
        ext = (".mp4", ".avi")[i % 2]
        path = root / f"video{i}{ext}"
        path.write_bytes(mutate(bases[ext], rng))
        add("video", run, ["--video", str(path), "--init", BOX, "--model", str(model), "--output",
                           str(root / f"v{i}.csv")], strict=False)
    for i in range(N_FOLDERS):
        folder = _sequence(root / f"seq{i}", _frames(6), (".jpg", ".png")[i % 2])
        for image in rng.sample(sorted((folder / "img").iterdir()), rng.randrange(1, 4)):
            image.write_bytes(mutate(image.read_bytes(), rng))
        add("frames", run, ["--video", str(folder), "--model", str(model), "--output", str(root / f"f{i}.csv")],
            strict=False)
    for i in range(N_MODELS):
        bad = _damaged_model(root / f"model{i}", model, rng, i)
        add("model", run, ["--video", str(root / "base.mp4"), "--init", BOX, "--model", str(bad), "--max-frames", "5"],
            strict=False)
    for i in range(N_RUN_CONFIGS):
        config = root / f"run{i}.toml"
        config.write_bytes(_run_config(rng))
        add("config", run, ["--config", str(config)], strict=True)
    for _ in range(N_HP):
        add("hp", run, ["--video", str(root / "base.mp4"), "--init", BOX, "--model", str(model), "--max-frames", "8",
                        "--hp", _hp(rng)], strict=False)
    for i in range(N_BENCH_MODELS):
        add("model", "dadiff.runtime.commands.bench", ["--model", str(root / f"model{3 * i}"), "--clip", "4",
                                                  "--max-frames", "2", "--warmup", "0", "--no-nano", "--json"],
            strict=False)
    dataset = root / "bench"
    _sequence(dataset / "seq001", _frames(8))
    for i in range(N_EVAL_MODELS):
        add("model", "dadiff.runtime.commands.eval", ["run", "--dataset", str(dataset), "--output",
            str(root / f"res{i}"), "--model", str(root / f"model{i}"), "--no-progress", "--no-plots"], strict=False)
    for i in range(N_EVAL_RESULTS):
        results = root / f"results{i}" / "T"
        results.mkdir(parents=True)
        truth = "".join(f"{40 + k},40,20,15\n" for k in range(8)).encode()
        (results / "seq001.txt").write_bytes(mutate(truth, rng))
        add("results", "dadiff.runtime.commands.eval", ["score", "--dataset", str(dataset), str(results)],
            strict=False)
    for i in range(N_EVAL_DATASETS):
        damaged = root / f"bench{i}"
        seq = _sequence(damaged / "seq001", _frames(8))
        target = seq / "groundtruth_rect.txt" if i % 2 else rng.choice(sorted((seq / "img").iterdir()))
        target.write_bytes(mutate(target.read_bytes(), rng))
        add("dataset", "dadiff.runtime.commands.eval", ["run", "--dataset", str(damaged), "--output",
            str(root / f"dres{i}"), "--model", str(model), "--no-progress", "--no-plots"], strict=False)
    _pseudo_label_cases(root, rng, add)
    return cases


def _pseudo_label_cases(root: Path, rng: random.Random, add: Any) -> None:
    """Damaged det.txt files against `dadiff-eval pseudo-label`, damaged detectors against `detect`."""
    from detector_models import write_fake_detector

    truth = "".join(f"{k + 1},-1,{40 + k},40,20,15,0.9,-1,-1,-1\n" for k in range(20)).encode()
    for i in range(N_DETECTIONS):
        det = root / f"det{i}.txt"
        det.write_bytes(mutate(truth, rng))
        add("detections", "dadiff.runtime.commands.eval", ["pseudo-label", "--video", str(root / "base.mp4"),
            "--detections", str(det), "--output", str(root / f"pl{i}"), "--min-frames", "5", "--aspect", "0.2-5",
            "--min-height", "10"], strict=False)
    good = write_fake_detector(root / "detector.onnx", [[0.3, 0.25, 0.45, 0.4]], [0.9], [1.0]).read_bytes()
    for i in range(N_DETECTORS):
        bad = root / f"detector{i}.onnx"
        bad.write_bytes(mutate(good, rng))
        add("detector", "dadiff.runtime.commands.eval", ["detect", "--video", str(root / "base.mp4"),
            "--detector", str(bad), "--output", str(root / f"det_out{i}.txt")], strict=False)


def _run_driver(cases: list[dict[str, Any]], root: Path, timeout: float, prefix: Sequence[str] = (),
                memory: int | None = None) -> list[dict[str, Any]]:
    """Run `cases` in one child (started through `prefix`, e.g. setpriv), its address space capped at `memory`
    bytes when given (an unbounded read then fails fast instead of filling the machine)."""
    def cap() -> None:
        if memory is not None:
            resource.setrlimit(resource.RLIMIT_AS, (memory, memory))

    (root / "cases.json").write_text(json.dumps(cases))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([*prefix, sys.executable, str(HERE / "fault_driver.py"), str(root / "cases.json"),
                           str(root / "results.jsonl")], capture_output=True, text=True, timeout=timeout, env=env,
                          preexec_fn=cap)
    results = [json.loads(line) for line in (root / "results.jsonl").read_text().splitlines()]
    assert proc.returncode == 0 and len(results) == len(cases), (proc.returncode, proc.stderr[-2000:])
    return results


def _verdict(case: dict[str, Any], result: dict[str, Any]) -> str | None:
    """What is wrong with one result, or None."""
    prog, code = PROGS[case["module"]], result["code"]
    if result["escaped"] == "hang":
        return "hang"
    if result["escaped"] is not None or "Traceback" in result["stderr"]:
        return "traceback: " + (result["escaped"] or result["stderr"])[-600:]
    if code != 2 and not (code == 0 and not case["strict"]):
        return f"exit {code}"
    errors = [line for line in result["stderr"].splitlines() if line.strip()]
    if code == 2 and not (len(errors) == 1 and errors[0].startswith(f"{prog}: error: ")):
        return f"not one error line: {errors}"
    lines = [line.strip() for line in result["stderr"].replace("\r", "\n").splitlines() if line.strip()]
    noise = [line for line in lines if not line.startswith(f"{prog}:") and "frame/s" not in line
             and "it/s" not in line and "frame [" not in line and "%|" not in line]
    if code == 0 and noise:
        return f"foreign lines on stderr: {noise[:3]}"  # a decoder talking past the one-line style
    return None


def _judge(cases: list[dict[str, Any]], results: list[dict[str, Any]]) -> dict[str, Any]:
    """Check every result; tally them per command and kind of input for the figures."""
    tally: dict[str, Any] = {}
    failures = []
    for case, result in zip(cases, results, strict=True):
        row = tally.setdefault(PROGS[case["module"]], {}).setdefault(
            case["kind"], {"cases": 0, "exit_2": 0, "exit_0": 0, "tracebacks": 0, "hangs": 0, "max_s": 0.0})
        verdict = _verdict(case, result)
        row["cases"] += 1
        row["max_s"] = max(row["max_s"], result["seconds"])
        row["hangs"] += verdict == "hang"
        row["tracebacks"] += bool(verdict and verdict.startswith("traceback"))
        row["exit_2"] += result["code"] == 2
        row["exit_0"] += result["code"] == 0
        if verdict:
            failures.append(f"{case['id']} {' '.join(case['argv'])}: {verdict}")
    assert not failures, "\n".join(failures)
    return tally


def test_damaged_files_against_the_onboard_commands(tmp_path) -> None:
    cases = _runtime_cases(tmp_path, random.Random(2026))
    started = time.monotonic()
    results = _run_driver(cases, tmp_path, timeout=300)
    FIGURES.setdefault("files", {}).update(_judge(cases, results))
    FIGURES["files_onboard_seconds"] = round(time.monotonic() - started, 1)


def _checkpoint_bytes(root: Path) -> tuple[bytes, dict[str, Any]]:
    import torch

    from dadiff.export.config import lite_config

    config = lite_config().to_dict()
    torch.save({"dadiff_format": 1, "config": config, "state_dict": {"w": torch.zeros(4)}}, root / "base.pt")
    return (root / "base.pt").read_bytes(), config


GARBAGE = (-1, 0, "x", [], {}, 1.5, True, float("nan"), "", [[1]])


def _bad_config(config: dict[str, Any], rng: random.Random) -> dict[str, Any]:
    """The stored model config with one key (or one tracker key) set to garbage, or one unknown key."""
    config = json.loads(json.dumps(config))
    if rng.random() < 0.15:
        config["no_such_key"] = 1
        return config
    table = config["tracker"] if rng.random() < 0.4 else config
    key = rng.choice(sorted(table))
    table[key] = rng.choice(GARBAGE)
    return config


def _train_config(rng: random.Random) -> str:
    """A dadiff-train config that must be refused before any work: a wrong type or range, or broken."""
    kind = rng.randrange(6)
    if kind == 0:
        return "steps = [\n"
    if kind == 1:
        return f"{rng.choice(('stepz', 'learning_rate', 'gpus'))} = 3\n"
    key, bad = rng.choice((
        ("steps", '"3"'), ("steps", "0"), ("steps", "-2"), ("batch_size", "1"), ("batch_size", '"2"'),
        ("lr", '"fast"'), ("lr", "0"), ("lr", "nan"), ("warmup_steps", '"x"'), ("warmup_steps", "1.5"),
        ("day", '"scenes"'), ("day", "[1, 2]"), ("day", "[{split = 1}]"), ("model", "{foo = 1}"),
        ("model", '{channels = "x"}'), ("model", "{ddim_steps = 0}"), ("checkpoint_every", "0"),
        ("stage", '"both"'), ("family", '"huge"'), ("optimizer", '"lbfgs"'), ("adversarial", "1"),
        ("grad_clip", "-1"), ("teacher", "5"), ("init", "[1]"), ("night", "true"), ("seed", '"s"'),
    ))
    return f'out = "OUT"\n{key} = {bad}\n' if kind != 2 else f'[train]\nout = "OUT"\n{key} = {bad}\n'


def _torch_cases(root: Path, rng: random.Random) -> list[dict[str, Any]]:
    from runtime_models import write_corr_model

    data, config = _checkpoint_bytes(root)
    cases: list[dict[str, Any]] = []

    def add(kind: str, module: str, argv: list[str]) -> None:
        cases.append({"id": f"{kind}-{len(cases)}", "kind": kind, "module": module, "argv": argv, "strict": True,
                      "limit": 120})

    import torch

    for i in range(N_CHECKPOINTS):
        path = root / f"ck{i}.pt"
        if i % 2:
            torch.save({"dadiff_format": 1, "config": _bad_config(config, rng), "state_dict": {"w": torch.zeros(4)}},
                       path)
        else:
            path.write_bytes(mutate(data, rng))
        add("checkpoint", "dadiff.export.cli", [str(path), "-o", str(root / f"out{i}")])
    model = write_corr_model(root / "model")
    for i in range(N_EXPORT_MODELS):
        folder = root / f"qmodel{i}"
        if i % 3 == 0:
            write_corr_model(folder, meta={"dadiff_format": None})
        else:
            folder.mkdir()
            for name in ("template.onnx", "search.onnx"):
                raw = (model / name).read_bytes()
                (folder / name).write_bytes(raw[: rng.randrange(len(raw) // 2)] if i % 3 == 1 else rng.randbytes(500))
        add("model", "dadiff.export.cli", [str(folder), "--quantize", "int8", "-o", str(root / f"q{i}")])
    for i in range(N_TRAIN_CONFIGS):
        path = root / f"train{i}.toml"
        path.write_text(_train_config(rng).replace("OUT", str(root / f"run{i}")))
        add("config", "dadiff.export.train_cli", ["--config", str(path)])
    return cases


def test_damaged_files_against_the_torch_commands(tmp_path) -> None:
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    cases = _torch_cases(tmp_path, random.Random(13))
    started = time.monotonic()
    results = _run_driver(cases, tmp_path, timeout=400)
    FIGURES.setdefault("files", {}).update(_judge(cases, results))
    FIGURES["files_torch_seconds"] = round(time.monotonic() - started, 1)
    assert not any((tmp_path / f"run{i}").exists() for i in range(N_TRAIN_CONFIGS))  # no training started


# ------------------------------------------------------------------- 2b. what a new user runs into (issue 55)

MEMORY_CAP = 4 << 30  # an unbounded read of /dev/zero then ends in MemoryError, not in the machine's OOM killer


def _new_user_cases(root: Path, held_port: int) -> list[dict[str, Any]]:
    """FIFOs and devices where a file belongs, damaged NanoTrack weights, MAVLink addresses that cannot work."""
    from dadiff.runtime.evaluation.evaluate import NANO_FILES
    from runtime_models import write_corr_model

    model = write_corr_model(root / "model")
    video = root / "base.mp4"
    _video(video, "mp4v")
    fifo = root / "fifo"
    os.mkfifo(fifo)
    dataset = root / "fifo-bench"
    _sequence(dataset / "seq001", _frames(8))
    (dataset / "seq001" / "groundtruth_rect.txt").unlink()
    os.mkfifo(dataset / "seq001" / "groundtruth_rect.txt")
    good = root / "bench"
    _sequence(good / "seq001", _frames(8))
    nano = root / "nano"
    nano.mkdir()
    for name in NANO_FILES:
        (nano / name).write_bytes(random.Random(55).randbytes(4000))
    cases: list[dict[str, Any]] = []

    def add(kind: str, module: str, argv: list[str], env: dict[str, str] | None = None) -> None:
        cases.append({"id": f"{kind}-{len(cases)}", "kind": kind, "module": module, "argv": argv, "strict": True,
                      "limit": 20, "env": env or {}})

    run, ev, bench = "dadiff.runtime.commands.run", "dadiff.runtime.commands.eval", "dadiff.runtime.commands.bench"
    track = ["--init", BOX, "--model", str(model), "--max-frames", "3"]
    service = ["--video", str(video), *track, "--mavlink"]
    add("fifo", run, ["--config", str(fifo)])
    add("fifo", run, ["--video", str(fifo), *track])
    add("fifo", run, ["--video", str(fifo), *track, "--mavlink", f"udpin:127.0.0.1:{free_port()}"])
    add("fifo", run, [*service, f"udpin:127.0.0.1:{free_port()}", "--signing-key", str(fifo)])
    add("fifo", ev, ["run", "--dataset", str(dataset), "--output", str(root / "fres"), "--model", str(model),
                     "--no-progress", "--no-plots"])
    add("fifo", "dadiff.export.train_cli", ["--config", str(fifo)])
    add("device", run, ["--config", "/dev/zero"])
    add("device", run, [*service, f"udpin:127.0.0.1:{free_port()}", "--signing-key", "/dev/zero"])
    add("device", "dadiff.export.train_cli", ["--config", "/dev/zero"])
    add("nano", ev, ["run", "--dataset", str(good), "--output", str(root / "nres"), "--tracker", "nano",
                     "--nano-dir", str(nano), "--no-progress", "--no-plots"])
    timing = ["--model", str(model), "--clip", "4", "--max-frames", "2", "--warmup", "0", "--json"]
    add("nano", bench, [*timing, "--nano-dir", str(nano)])
    add("nano", bench, timing, env={"DADIFF_NANO_DIR": str(nano)})
    add("mavlink", run, [*service, "udpin:999.1.1.1:14550"])
    add("mavlink", run, [*service, "udpout:no-such-host.invalid:14550"])
    add("mavlink", run, [*service, f"udpin:127.0.0.1:{held_port}"])  # the port another service holds
    add("mavlink", run, [*service, f"udpin:0.0.0.0:{held_port}"])
    add("mavlink", run, [*service, f"udp:127.0.0.1:{held_port}"])  # pymavlink's plain udp: listens too
    return cases


def test_new_user_faults_are_one_line_without_hang(tmp_path) -> None:
    pytest.importorskip("torch")
    held = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    held.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as pymavlink binds udpin: sharing allowed
    held.bind(("127.0.0.1", 0))
    try:
        cases = _new_user_cases(tmp_path, held.getsockname()[1])
        results = _run_driver(cases, tmp_path, timeout=300, memory=MEMORY_CAP)
    finally:
        held.close()
    FIGURES["new_user"] = _judge(cases, results)
    assert not (tmp_path / "nres").exists()  # refused before the run's record was written


def _without_root_reads() -> list[str] | None:
    """How to start a child that file permissions bind: as is for a user, without root's read-anything
    capabilities for root (setpriv); None where neither works."""
    import shutil
    import subprocess

    if os.geteuid() != 0:
        return []
    prefix = ["setpriv", "--bounding-set", "-dac_override,-dac_read_search"]
    if shutil.which("setpriv") and subprocess.run([*prefix, "true"], capture_output=True).returncode == 0:
        return prefix
    return None


def test_inputs_the_user_may_not_read_are_one_line(tmp_path) -> None:
    prefix = _without_root_reads()
    if prefix is None:
        pytest.skip("root without setpriv: permissions do not bind here")
    from runtime_models import write_corr_model

    model = write_corr_model(tmp_path / "model")
    seq = _sequence(tmp_path / "locked", _frames(6))
    config = tmp_path / "locked.toml"
    config.write_text(f'video = "{seq}"\n')
    add = {"strict": True, "limit": 30}
    run = "dadiff.runtime.commands.run"
    cases = [
        {"id": "folder-0", "kind": "unreadable", "module": run, "argv": ["--video", str(seq), "--model", str(model)]},
        {"id": "folder-1", "kind": "unreadable", "module": run, "argv": [
            "--video", str(seq), "--model", str(model), "--mavlink", f"udpin:127.0.0.1:{free_port()}"]},
        {"id": "folder-2", "kind": "unreadable", "module": "dadiff.runtime.commands.eval", "argv": [
            "run", "--dataset", str(tmp_path / "locked"), "--output", str(tmp_path / "res"), "--model", str(model),
            "--no-progress", "--no-plots"]},
        {"id": "config-3", "kind": "unreadable", "module": run, "argv": ["--config", str(config)]},
    ]
    cases = [{**case, **add} for case in cases]
    (seq / "img").chmod(0o000)  # as a chmod 700 folder of another user
    config.chmod(0o000)
    try:
        results = _run_driver(cases, tmp_path, timeout=120, prefix=prefix)
    finally:
        (seq / "img").chmod(0o755)
        config.chmod(0o644)
    FIGURES["unreadable"] = _judge(cases, results)

# ------------------------------------------------------------------- 4. endings: a full disk and signals

FULL_DISK_BYTES = 4096  # RLIMIT_FSIZE: a write past it fails part-way (EFBIG), as one onto a full disk does
ENTRY_POINTS = tomllib.loads((HERE.parent / "pyproject.toml").read_text())["project"]["scripts"]  # prog -> mod:fn
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _command(prog: str, argv: list[str], **kwargs: Any) -> subprocess.Popen:
    """`prog` started as its console script starts it (runtime/commands/launch.py), in a child process."""
    module, function = ENTRY_POINTS[prog].split(":")
    code = f"import sys; from {module} import {function} as entry; sys.exit(entry())"  # as the console script
    env = {**os.environ, **kwargs.pop("env", {})}
    before = kwargs.pop("preexec_fn", None)

    def child() -> None:
        hangup_as_in_a_session()
        if before is not None:
            before()

    return subprocess.Popen([sys.executable, "-c", code, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, preexec_fn=child, **kwargs)


def _small_disk() -> None:
    """In the child: every file it writes ends at FULL_DISK_BYTES (EFBIG instead of SIGXFSZ)."""
    resource.setrlimit(resource.RLIMIT_FSIZE, (FULL_DISK_BYTES, FULL_DISK_BYTES))
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)


def _long_video(path: Path, frames: int) -> Path:
    import cv2

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (160, 120))
    base = _frames(20)
    for i in range(frames):
        writer.write(base[i % 20])
    writer.release()
    return path


def _video_frames(path: Path) -> int:
    import cv2

    capture = cv2.VideoCapture(str(path))
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) if capture.isOpened() else 0
    capture.release()
    return count


def _whole_rows(path: Path) -> int:
    """Rows of a track log, each checked whole (CSV: 8 fields; JSONL: one object); -1 for a cut one."""
    if not path.exists():
        return 0
    text = path.read_text()
    if text and not text.endswith("\n"):
        return -1
    lines = text.splitlines()
    if path.suffix == ".csv":
        return len(lines) - 1 if all(len(line.split(",")) == 8 for line in lines) else -1
    try:
        return sum(isinstance(json.loads(line), dict) for line in lines)
    except ValueError:
        return -1


def _one_error_naming(stderr: str, prog: str, path: Path) -> bool:
    lines = [line for line in stderr.splitlines() if line.strip()]
    return len(lines) == 1 and lines[0].startswith(f"{prog}: error: ") and str(path) in lines[0]


def test_full_disk_leaves_outputs_whole_or_removed(tmp_path) -> None:
    """Every output a command writes, onto a disk that fills: exit != 0, one line naming the file, and the file
    valid up to its last whole row (track logs) or removed (videos; eval's result files, no `.tmp` left)."""
    from runtime_models import write_corr_model

    model = write_corr_model(tmp_path / "model")
    video = _long_video(tmp_path / "clip.mp4", 200)
    dataset = tmp_path / "bench"
    seq = dataset / "seq001"
    (seq / "img").mkdir(parents=True)
    for k in range(300):
        (seq / "img" / f"{k + 1:04d}.png").symlink_to(tmp_path / "frame.png")
    import cv2

    cv2.imwrite(str(tmp_path / "frame.png"), _frames(1)[0])
    (seq / "groundtruth_rect.txt").write_text("40,40,20,15\n" * 300)
    out = tmp_path / "out"
    out.mkdir()
    run = ["--video", str(video), "--init", BOX, "--model", str(model)]
    cases = [
        ("dadiff-run", [*run, "--output", str(out / "log.csv")], out / "log.csv"),
        ("dadiff-run", [*run, "--output", str(out / "log.jsonl")], out / "log.jsonl"),
        ("dadiff-run", [*run, "--save-video", str(out / "track.mp4")], out / "track.mp4"),
        *([("dadiff-run", ["--demo", "--demo-out", str(out / "demo"), "--model", str(model)],
            out / "demo" / "demo-night-0.mp4"),  # the generator needs dadiff[eval] (scikit-image)
           ("dadiff-bench", ["--model", str(model), "--clip", "20", "--max-frames", "5", "--warmup", "0", "--no-nano"],
            out / "bench-tmp")] if importlib.util.find_spec("skimage") else []),  # its clip goes to TMPDIR
        ("dadiff-eval", ["run", "--dataset", str(dataset), "--output", str(out / "results"), "--model", str(model),
                         "--no-progress", "--no-plots"], out / "results"),
    ]
    failures, tally = [], {"cases": len(cases), "exit_nonzero": 0, "one_line_naming_the_file": 0,
                           "damaged_files_left": 0}
    (out / "bench-tmp").mkdir()
    for prog, argv, path in cases:
        proc = _command(prog, argv, preexec_fn=_small_disk, env={"TMPDIR": str(out / "bench-tmp")})
        _, err = proc.communicate(timeout=120)
        tally["exit_nonzero"] += proc.returncode != 0
        tally["one_line_naming_the_file"] += _one_error_naming(err, prog, path)
        if path.suffix in (".csv", ".jsonl"):
            damaged = _whole_rows(path) < 0
        elif path.suffix == ".mp4":
            damaged = path.exists() and _video_frames(path) == 0
        elif path.name == "bench-tmp":  # dadiff-bench's clip, in a temporary folder that must be gone
            damaged = any(path.glob("dadiff-bench-*"))
        else:  # eval's results: written whole through a temporary file, which must not stay behind
            damaged = any(p.name.endswith(".tmp") for p in path.rglob("*"))
        tally["damaged_files_left"] += damaged
        if proc.returncode == 0 or damaged or not _one_error_naming(err, prog, path):
            failures.append(f"{prog} {' '.join(argv)}: exit {proc.returncode}, damaged {damaged}, stderr {err!r}")
    FIGURES["full_disk"] = tally
    assert not failures, "\n".join(failures)


def test_full_disk_on_the_log_file_is_one_warning_not_a_traceback_per_record(tmp_path, capfd) -> None:
    """The service's --log-file on a full disk (/dev/full): one warning naming it, not 50 tracebacks."""
    from dadiff.drone.logs import log_handlers, service_logging

    records = 50
    with service_logging("INFO", log_handlers(Path("/dev/full"))) as logger:
        for i in range(records):
            logger.info("record %d", i)
    err = capfd.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    FIGURES["full_disk_log"] = {"records": records, "stderr_lines": len(lines)}
    assert len(lines) == 1 and "/dev/full: cannot write the log (No space left on device)" in lines[0], lines


@pytest.mark.parametrize("sig", STOP_SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_signal_mid_run_finalises_the_video_and_prints_the_summary(tmp_path, sig) -> None:
    """SIGINT, SIGTERM and SIGHUP (an SSH session dropping) during `dadiff-run --save-video --output`: exit 130,
    the summary, a CSV of whole rows and an MP4 that holds one frame per row."""
    from runtime_models import write_corr_model

    model = write_corr_model(tmp_path / "model")
    video = _long_video(tmp_path / "clip.mp4", 1500)
    log, mp4 = tmp_path / "log.csv", tmp_path / "track.mp4"
    proc = _command("dadiff-run", ["--video", str(video), "--init", BOX, "--model", str(model), "--output", str(log),
                                   "--save-video", str(mp4)])
    assert wait_until(lambda: log.exists() and log.stat().st_size > 2000, 60)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=60)
    rows = _whole_rows(log)
    FIGURES.setdefault("signals_mid_run", {})[signal.Signals(sig).name] = {
        "exit": proc.returncode, "rows": rows, "video_frames": _video_frames(mp4)}
    assert proc.returncode == 130, err
    assert "dadiff-run: interrupted" not in err and "frames," in out  # the summary, not the early-exit line
    assert 0 < rows < 1500 and _video_frames(mp4) == rows


def test_signal_while_a_command_imports_is_one_line(tmp_path) -> None:
    """Ctrl-C, SIGTERM or SIGHUP before a command's `main` runs (while OpenCV or torch import: seconds on a
    small computer): one `<command>: interrupted` line and exit 130, never a traceback or death by signal."""
    slow = tmp_path / "slow"
    for module in ("cv2", "torch"):  # the first heavy import of every command, held until the signal comes
        (slow / module).mkdir(parents=True)
        (slow / module / "__init__.py").write_text(
            "import os, time\n"
            f"open(os.path.join({str(tmp_path)!r}, 'importing'), 'w').close()\n"
            "time.sleep(60)\n")
    env = {"PYTHONPATH": os.pathsep.join([str(slow), os.environ.get("PYTHONPATH", "")])}
    failures, tried = [], 0
    for prog in ENTRY_POINTS:
        for sig in STOP_SIGNALS:
            (tmp_path / "importing").unlink(missing_ok=True)
            argv = {"dadiff-run": ["--video", "x.mp4"], "dadiff-train": ["--config", "x.toml"]}.get(prog, ["x"])
            proc = _command(prog, argv, env=env)
            assert wait_until(lambda: (tmp_path / "importing").exists(), 30), prog
            proc.send_signal(sig)
            _, err = proc.communicate(timeout=30)
            tried += 1
            if proc.returncode != 130 or err.strip() != f"{prog}: interrupted":
                failures.append(f"{prog} {signal.Signals(sig).name}: exit {proc.returncode}, stderr {err[-300:]!r}")
    FIGURES["signals_while_importing"] = {"cases": tried, "failures": len(failures)}
    assert not failures, "\n".join(failures)


# ---------------------------------------------------------------------------------------------- 3. soak

SOAK_FRAMES = 10_000
CAMERA_LIFE_S = 1.0  # each camera "connection" delivers frames for this long, then drops
LINK_LIFE_S = 1.5  # the autopilot (TCP server) goes away this often, for LINK_DOWN_S
LINK_DOWN_S = 0.3


class DroppingCamera:
    """A live source delivering frames as fast as ~2 kHz for CAMERA_LIFE_S, then ending (the camera drops);
    records when each connection delivered its first frame and ended."""

    live = True

    def __init__(self, log: list[tuple[float, float]]) -> None:
        self.log, self.closed = log, False

    def frames(self) -> Iterator[Frame]:
        image = np.full((120, 160, 3), 90, np.uint8)
        first = time.monotonic()
        index = 0
        while not self.closed and time.monotonic() - first < CAMERA_LIFE_S:
            yield Frame(index, time.time(), image)
            index += 1
            time.sleep(0.0004)
        self.log.append((first, time.monotonic()))

    def close(self) -> None:
        self.closed = True


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def _link_flapper(port: int, stop: threading.Event, reconnects: list[float]) -> None:
    """Restart the autopilot (a TCP server) every LINK_LIFE_S; measure how soon the camera heartbeats again."""
    url = f"tcpin:127.0.0.1:{port}"
    while not stop.is_set():
        peer = Autopilot(url, rate=5.0).start()
        up = time.monotonic()
        if wait_until(lambda p=peer, t=up: bool(p.received("HEARTBEAT", t, src_component=100)), 5):
            reconnects.append(peer.received("HEARTBEAT", up, src_component=100)[0].at - up)
        stop.wait(max(0.0, LINK_LIFE_S - (time.monotonic() - up)))
        peer.close()
        stop.wait(LINK_DOWN_S)


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="needs /proc for the memory figure")
def test_soak_loses_no_row_while_camera_and_link_drop(tmp_path) -> None:
    port = free_port(socket.SOCK_STREAM)
    tracker = FakeTracker()
    tracker.drift = 0.0
    cameras: list[tuple[float, float]] = []
    log = TrackLog(tmp_path / "soak.csv")
    link = LinkSettings(f"tcp:127.0.0.1:{port}", retry_min=0.05, retry_max=0.2, silence_timeout=1.0)
    settings = ServiceSettings(link, heartbeat_hz=5.0, init_box=(70.0, 50.0, 20.0, 20.0), video_retry=(0.05, 0.1),
                               status_every=3600)
    service = Service(settings, tracker, lambda: DroppingCamera(cameras), [log])
    stop, link_reconnects = threading.Event(), []
    flapper = threading.Thread(target=_link_flapper, args=(port, stop, link_reconnects), daemon=True)
    runner = threading.Thread(target=service.run, daemon=True)
    started = time.monotonic()
    flapper.start()
    runner.start()
    try:
        assert wait_until(lambda: len(tracker.updates) >= 1000, 30)
        rss_start = _rss_mb()
        assert wait_until(lambda: len(tracker.updates) >= SOAK_FRAMES, 90), len(tracker.updates)
        rss_end = _rss_mb()
    finally:
        service.stop()
        stop.set()
        runner.join(10)
        flapper.join(10)
    seconds = time.monotonic() - started
    assert not runner.is_alive()
    rows = (tmp_path / "soak.csv").read_text().splitlines()[1:]
    processed = len(tracker.updates) + len(tracker.inits)
    gaps = [b[0] - a[1] for a, b in zip(cameras, cameras[1:], strict=False)]
    FIGURES["soak"] = {
        "frames_tracked": len(tracker.updates), "rows_written": len(rows), "rows_lost": processed - len(rows),
        "seconds": round(seconds, 1), "camera_drops": len(cameras), "camera_reconnect_ms_p50": _ms(gaps, 50),
        "camera_reconnect_ms_max": _ms(gaps, 100), "link_drops": len(link_reconnects),
        "link_reconnect_ms_p50": _ms(link_reconnects, 50), "link_reconnect_ms_max": _ms(link_reconnects, 100),
        "rss_mb_at_1000_frames": round(rss_start, 1), "rss_mb_at_end": round(rss_end, 1),
        "frames_dropped_by_grabber": service.grabber.dropped, "link_opens": service.link.opens,
        "tracker_inits": len(tracker.inits),
    }
    assert len(rows) == processed  # every frame the tracker saw has its row
    assert len(cameras) >= 3 and len(link_reconnects) >= 3
    assert len(tracker.inits) == 1  # the target survived every drop
    assert rss_end - rss_start < 25, FIGURES["soak"]
    assert max(link_reconnects) < 3.0 and max(gaps) < 1.0


def _ms(values: list[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)) * 1000, 1) if values else None


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q", "-s"]))

"""dadiff-run: outputs for a video file and a sequence folder, skipped frames, Ctrl-C, one-line errors."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime import Tracker
from dadiff.runtime.commands import run as cli
from runtime_models import write_corr_model
from runtime_scenes import iou, moving_sequence

N_FRAMES = 24


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("cli")
    frames, boxes = moving_sequence(N_FRAMES)
    video = root / "clip.mp4"
    writer = cv2.VideoWriter(
        str(video), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (frames[0].shape[1], frames[0].shape[0])
    )
    for frame in frames:
        writer.write(frame)
    writer.release()
    seq = root / "seq"
    (seq / "img").mkdir(parents=True)
    for k, frame in enumerate(frames):
        cv2.imwrite(str(seq / "img" / f"{k + 1:04d}.png"), frame)
    (seq / "groundtruth_rect.txt").write_text("".join("\t".join(map(str, b)) + "\n" for b in boxes))
    bad_meta = write_corr_model(root / "nometa", meta={"dadiff_format": None, "exemplar_size": None})
    corrupt = write_corr_model(root / "corrupt")
    (corrupt / "template.onnx").write_bytes(b"not an onnx file at all")
    not_video = root / "notes.mp4"
    not_video.write_text("this is not a video\n")
    empty = root / "empty"
    empty.mkdir()
    return {
        "root": root,
        "video": video,
        "seq": seq,
        "model": write_corr_model(root / "model"),
        "nometa": bad_meta,
        "corrupt": corrupt,
        "not_video": not_video,
        "empty": empty,
    }


def _read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _video_frames(path: Path) -> int:
    cap = cv2.VideoCapture(str(path))
    count = 0
    while cap.read()[0]:
        count += 1
    cap.release()
    return count


def test_video_file_to_csv_and_mp4(
    data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    out_csv, out_mp4 = tmp_path / "track.csv", tmp_path / "annotated.mp4"
    rc = cli.main(
        [
            "--video",
            str(data["video"]),
            "--init",
            "220,160,40,40",
            "--model",
            str(data["model"]),
            "--threads",
            "1",
            "--output",
            str(out_csv),
            "--save-video",
            str(out_mp4),
        ]
    )
    assert rc == 0
    rows = _read_csv(out_csv)
    assert len(rows) == N_FRAMES
    assert list(rows[0]) == ["frame", "timestamp", "x", "y", "w", "h", "score", "state"]
    assert [int(r["frame"]) for r in rows] == list(range(N_FRAMES))
    # frame 0 is the init box in the released toolkit's convention (x + 0.5, y + 0.5, w, h)
    assert [float(rows[0][k]) for k in "xywh"] == [220.5, 160.5, 40.0, 40.0] and rows[0]["state"] == "init"
    assert float(rows[1]["timestamp"]) == pytest.approx(1 / 25)
    assert {r["state"] for r in rows[1:]} == {"tracking"}
    assert _video_frames(out_mp4) == N_FRAMES
    summary = capsys.readouterr().out
    assert f"{N_FRAMES} frames, 0 lost, 0 skipped" in summary and "p50" in summary and "p95" in summary


@pytest.mark.parametrize("separator", ["\t", ",", " "])
def test_sequence_folder_uses_groundtruth(
    data: dict[str, Path], tmp_path: Path, separator: str, capsys: pytest.CaptureFixture
) -> None:
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "img").symlink_to(data["seq"] / "img")
    lines = (data["seq"] / "groundtruth_rect.txt").read_text().replace("\t", separator)
    (seq / "groundtruth_rect.txt").write_text(lines)
    out = tmp_path / "track.jsonl"
    assert (
        cli.main(["--video", str(seq), "--model", str(data["model"]), "--threads", "1", "--output", str(out)])
        == 0
    )
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(rows) == N_FRAMES
    gt = [tuple(map(float, line.split(separator))) for line in lines.splitlines()]
    assert (rows[0]["x"], rows[0]["y"]) == (gt[0][0] + 0.5, gt[0][1] + 0.5)
    assert np.mean([iou((r["x"], r["y"], r["w"], r["h"]), g) for r, g in zip(rows, gt, strict=True)]) > 0.7


def test_max_frames_and_bad_image_skipped(
    data: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    seq = tmp_path / "seq"
    (seq / "img").mkdir(parents=True)
    for image in sorted((data["seq"] / "img").iterdir()):
        (seq / "img" / image.name).write_bytes(image.read_bytes())
    (seq / "img" / "0005.png").write_bytes(b"\x89PNG broken")
    (seq / "groundtruth_rect.txt").write_text((data["seq"] / "groundtruth_rect.txt").read_text())
    out = tmp_path / "track.csv"
    assert cli.main(["--video", str(seq), "--model", str(data["model"]), "--output", str(out)]) == 0
    rows = _read_csv(out)
    assert len(rows) == N_FRAMES - 1 and "4" not in [r["frame"] for r in rows]
    assert f"{N_FRAMES - 1} frames, 0 lost, 1 skipped" in capsys.readouterr().out
    assert (
        cli.main(
            ["--video", str(seq), "--model", str(data["model"]), "--output", str(out), "--max-frames", "10"]
        )
        == 0
    )
    assert len(_read_csv(out)) == 10


def test_ctrl_c_flushes_outputs(
    data: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    real_update, calls = Tracker.update, []

    def update(self: Tracker, frame: np.ndarray):  # noqa: ANN202
        calls.append(1)
        if len(calls) == 8:
            raise KeyboardInterrupt
        return real_update(self, frame)

    monkeypatch.setattr(Tracker, "update", update)
    out_csv, out_mp4 = tmp_path / "t.csv", tmp_path / "t.mp4"
    rc = cli.main(
        [
            "--video",
            str(data["seq"]),
            "--model",
            str(data["model"]),
            "--output",
            str(out_csv),
            "--save-video",
            str(out_mp4),
        ]
    )
    assert rc == 130
    assert len(_read_csv(out_csv)) == 8  # init frame + 7 tracked
    assert _video_frames(out_mp4) == 8
    assert "8 frames" in capsys.readouterr().out


BAD_INPUTS = [
    (["--model", "{root}/missing"], "model '{root}/missing' not found"),
    (["--model", "{nometa}"], "metadata key 'dadiff_format' is missing"),
    (["--model", "{corrupt}"], "template.onnx: not a loadable ONNX model"),
    (["--model", "{model}", "--init", "220,160,0,40"], "zero or negative size"),
    (["--model", "{model}", "--init", "900,160,40,40"], "outside the 480x360 frame"),
    (["--model", "{model}", "--video", "{not_video}"], "cannot read video file"),
    (["--model", "{model}", "--video", "{root}/nope.mp4"], "no such file or folder"),
    (["--model", "{model}", "--video", "{empty}"], "no image files found"),
    (["--model", "{model}", "--init", "1,2,3"], "argument --init: expected four numbers"),
    (["--model", "{model}", "--hp", "lr"], "argument --hp: expected key=value"),
    (["--model", "{model}", "--hp", "lr=0.3,speed=2"], "unknown override 'speed'"),
    (["--model", "{model}", "--preset", "NIGHT"], "unknown preset 'NIGHT'"),
    (["--model", "{model}", "--provider", "nope"], "provider 'nope' is not available"),
    (["--model", "{model}", "--output", "{root}/t.txt"], "--output must end in .csv or .jsonl"),
    (["--model", "{model}", "--threads", "0"], "argument --threads: expected an integer of at least 1, got '0'"),
]


@pytest.mark.parametrize(("args", "message"), BAD_INPUTS)
def test_bad_input_one_line_exit_2(
    data: dict[str, Path], args: list[str], message: str, capsys: pytest.CaptureFixture
) -> None:
    fill = {k: str(v) for k, v in data.items()}
    argv = [a.format(**fill) for a in args]
    if "--video" not in argv:
        argv += ["--video", str(data["video"])]
    if "--init" not in argv:
        argv += ["--init", "220,160,40,40"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("dadiff-run: error: ")
    assert message.format(**fill) in err[0]


def test_video_needs_init(data: dict[str, Path], capsys: pytest.CaptureFixture) -> None:
    assert cli.main(["--video", str(data["video"]), "--model", str(data["model"])]) == 2
    assert "no --init x,y,w,h given" in capsys.readouterr().err


def test_console_error_is_one_line_without_traceback(data: dict[str, Path]) -> None:
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "dadiff.runtime.commands.run",
            "--video",
            str(data["not_video"]),
            "--init",
            "1,1,5,5",
            "--model",
            str(data["model"]),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"dadiff-run: error: cannot read video file '{data['not_video']}'"
    ]


def test_no_default_model_is_one_line(data: dict[str, Path], no_shipped_model, capsys: pytest.CaptureFixture) -> None:
    assert cli.main(["--video", str(data["video"]), "--init", "220,160,40,40"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no trained default model is shipped yet" in err[0]

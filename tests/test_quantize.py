"""`dadiff-export --quantize int8`: the int8 graph's structure and metadata, the runtime on it, the CLI and its
errors. Tiny calibration and evaluation sets keep every test to a few seconds; nothing here times anything."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
pytest.importorskip("torch")
pytest.importorskip("skimage")

from dadiff.export.cli import main  # noqa: E402
from dadiff.export.quantize import QuantizeError, QuantizeSettings, quantize_model, read_metadata  # noqa: E402
from dadiff.runtime import Tracker  # noqa: E402
from dadiff.runtime.config import REQUIRED_KEYS, TUNABLE_KEYS  # noqa: E402
from dadiff.runtime.datamaking.scenes import make_sequence  # noqa: E402

TINY = QuantizeSettings(frames=4, eval_sequences=1, eval_frames=3, bench_runs=0)
TINY_ARGS = ["--calibration-frames", "3", "--eval-sequences", "1", "--max-frames", "3", "--bench-runs", "0"]


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    try:
        code = main(list(argv))
    except SystemExit as exc:  # a usage error, found by the argument parser
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def int8_dir(tmp_path_factory, lite_model_dir) -> Path:
    out = tmp_path_factory.mktemp("int8") / "lite-int8"
    quantize_model(lite_model_dir, out, TINY, log=lambda _line: None)
    return out


@pytest.fixture(scope="module")
def calibration_media(tmp_path_factory) -> dict[str, Path | str]:
    """A night sequence folder with ground truth, and the same frames as a video without any."""
    root = tmp_path_factory.mktemp("calibration")
    seq = make_sequence(11, split="train", frames=5, size=(320, 240))
    folder = root / "seq"
    (folder / "img").mkdir(parents=True)
    for k, frame in enumerate(seq.night):
        cv2.imwrite(str(folder / "img" / f"{k + 1:04d}.png"), frame)
    (folder / "groundtruth_rect.txt").write_text("".join(",".join(f"{v:.2f}" for v in b) + "\n" for b in seq.boxes))
    video = root / "clip.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (320, 240))
    for frame in seq.night:
        writer.write(frame)
    writer.release()
    return {"folder": folder, "video": video, "box": ",".join(f"{v:.1f}" for v in seq.boxes[0])}


def test_int8_search_graph_is_qdq_with_per_channel_weights_and_no_random_ops(int8_dir):
    model = onnx.load(str(int8_dir / "search.onnx"))
    ops = [n.op_type for n in model.graph.node]
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    assert not [op for op in ops if op.startswith("Random")]
    inits = {i.name: i for i in model.graph.initializer}
    per_channel = [
        n for n in model.graph.node
        if n.op_type == "DequantizeLinear" and n.input[0] in inits
        and inits[n.input[0]].data_type == onnx.TensorProto.INT8 and len(inits[n.input[1]].dims) == 1
        and inits[n.input[1]].dims[0] > 1 and any(a.name == "axis" for a in n.attribute)
    ]
    assert len(per_channel) >= 10  # conv weights: int8, one scale per output channel
    assert [i.name for i in model.graph.input] == ["x", "kcls0", "kloc0"]


def test_metadata_marks_int8_and_agrees_with_the_template(int8_dir, lite_model_dir):
    search, template = read_metadata(int8_dir / "search.onnx"), read_metadata(int8_dir / "template.onnx")
    assert search["precision"] == "int8" and search["graph"] == "search" and template["graph"] == "template"
    assert search["name"] == template["name"] + "-int8"  # told apart from its fp32 source in reports
    for key in (*REQUIRED_KEYS, *TUNABLE_KEYS, "hp_presets", "channel_order"):
        assert search.get(key) == template.get(key), key
    info = json.loads(search["quantization"])
    assert info["recipe"] and info["method"] == "minmax" and info["calibration_frames"] == 4
    assert "train split" in info["calibration"]
    assert set(info["deviation"]) >= {"cls_max_abs", "cls_mean_abs", "loc_max_abs", "loc_mean_abs", "cell_agreement",
                                      "cell_within_one"}
    assert "test split" in info["success"]["set"] and 0 <= info["success"]["int8"] <= 1
    assert (int8_dir / "template.onnx").read_bytes() == (lite_model_dir / "template.onnx").read_bytes()


def test_runtime_loads_and_tracks_with_the_int8_model(int8_dir):
    tracker = Tracker.load(int8_dir, threads=1)
    seq = make_sequence(5, split="test", frames=4)
    tracker.init(seq.night[0], tuple(seq.boxes[0]))
    for frame in seq.night[1:]:
        result = tracker.update(frame)
        assert all(math.isfinite(v) for v in result.box) and 0.0 <= result.score <= 1.0


def test_cli_quantizes_a_model_folder(tmp_path, capsys, lite_model_dir):
    out = tmp_path / "q"
    code, stdout, err = _run(capsys, str(lite_model_dir), "--quantize", "int8", "-o", str(out), *TINY_ARGS)
    assert code == 0, err
    assert "deviation from fp32" in stdout and "night success" in stdout and "fp32" in stdout
    assert read_metadata(out / "search.onnx")["precision"] == "int8"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".dadiff-quantize-")]


def test_cli_calibrates_on_a_sequence_folder(tmp_path, capsys, lite_model_dir, calibration_media):
    out = tmp_path / "q"
    code, _, err = _run(capsys, str(lite_model_dir), "--quantize", "int8", "-o", str(out), *TINY_ARGS,
                        "--calibration", str(calibration_media["folder"]))
    assert code == 0, err
    info = json.loads(read_metadata(out / "search.onnx")["quantization"])
    assert info["calibration"] == str(calibration_media["folder"]) and info["calibration_frames"] == 3


def test_cli_exports_and_quantizes_a_checkpoint(tmp_path, capsys, lite_checkpoint):
    out = tmp_path / "ckpt-int8"
    code, stdout, err = _run(capsys, str(lite_checkpoint), "--quantize", "int8", "-o", str(out), *TINY_ARGS)
    assert code == 0, err
    assert "parity torch vs onnxruntime" in stdout and "night success" in stdout
    assert sorted(p.name for p in out.iterdir()) == ["search.onnx", "template.onnx"]
    assert read_metadata(out / "search.onnx")["precision"] == "int8"


@pytest.mark.parametrize("argv, expected", [
    (["--quantize", "int4"], "unsupported precision"),
    (["--quantize", "int8", "--calibration", "{tmp}/missing.mp4"], "no such file or folder"),
    (["--quantize", "int8", "--calibration", "{folder}", "--calibration-init", "1,2,3"], "--calibration-init"),
    (["--quantize", "int8", "--calibration", "{folder}", "--calibration-init", "1,2,0,5"], "must be positive"),
    (["--quantize", "int8", "--calibration", "{video}"], "give --calibration-init"),
    (["--quantize", "int8", "--calibration-init", "1,2,3,4"], "applies to --calibration"),
    (["--quantize", "int8", "--calibration-frames", "0"], "--calibration-frames: expected an integer from 1 to 2000"),
    (["--quantize", "int8", "--calibration-frames", "1000000000"], "--calibration-frames: expected an integer "
                                                                    "from 1 to 2000, got '1000000000'"),
    (["--calibration", "{folder}"], "applies to --quantize int8 only"),
    (["--quantize", "int8", "--steps", "3"], "applies to checkpoints"),
])
def test_bad_quantize_options_are_one_line_and_exit_2(tmp_path, capsys, lite_model_dir, calibration_media,
                                                      argv, expected):
    values = {"tmp": tmp_path, "folder": calibration_media["folder"], "video": calibration_media["video"]}
    argv = [a.format(**values) for a in argv]
    code, _, err = _run(capsys, str(lite_model_dir), "-o", str(tmp_path / "out"), *argv)
    assert code == 2
    assert err.startswith("dadiff-export: error: ") and err.count("\n") == 1 and expected in err, err
    assert not (tmp_path / "out").exists()


def test_cli_calibrates_on_a_video_with_an_init_box(tmp_path, capsys, lite_model_dir, calibration_media):
    out = tmp_path / "q"
    code, _, err = _run(capsys, str(lite_model_dir), "--quantize", "int8", "-o", str(out), *TINY_ARGS,
                        "--calibration", str(calibration_media["video"]),
                        "--calibration-init", str(calibration_media["box"]))
    assert code == 0, err
    assert json.loads(read_metadata(out / "search.onnx")["quantization"])["calibration_frames"] == 3


def test_an_int8_model_is_not_quantised_again(tmp_path, int8_dir):
    with pytest.raises(QuantizeError, match="already quantised"):
        quantize_model(int8_dir, tmp_path / "again", TINY, log=lambda _line: None)


def test_checkpoint_export_is_skipped_when_the_options_are_wrong(tmp_path, capsys, lite_checkpoint):
    code, stdout, err = _run(capsys, str(lite_checkpoint), "--quantize", "int8", "-o", str(tmp_path / "m"),
                             "--calibration", str(tmp_path / "nope"))
    assert code == 2 and "no such file or folder" in err and "parity" not in stdout


def test_model_folder_without_quantize_says_how(capsys, lite_model_dir):
    code, _, err = _run(capsys, str(lite_model_dir))
    assert code == 2 and "add --quantize int8" in err and err.count("\n") == 1


def test_calibration_frames_are_bounded_for_api_callers_too(tmp_path, lite_model_dir):
    too_many = dataclasses.replace(TINY, frames=10**9)  # grew memory without end before any check
    with pytest.raises(QuantizeError, match="calibration frames must be at most 2000, got 1000000000"):
        quantize_model(lite_model_dir, tmp_path / "q", too_many, log=lambda _line: None)
    assert not (tmp_path / "q").exists()


def test_refuses_to_overwrite_its_source(lite_model_dir):
    with pytest.raises(QuantizeError, match="fp32 source folder"):
        quantize_model(lite_model_dir, lite_model_dir, TINY, log=lambda _line: None)


def test_feeds_recorded_are_what_the_search_graph_takes(lite_model_dir):
    from dadiff.export.quantize import generated_sequences, record_search_inputs

    feeds = record_search_inputs(lite_model_dir, generated_sequences(2), 2)
    assert len(feeds) == 2
    for feed in feeds:
        assert list(feed) == ["x", "kcls0", "kloc0"] and feed["x"].shape == (1, 3, 255, 255)
        assert feed["x"].dtype == np.float32 and 0 <= feed["x"].min() and feed["x"].max() <= 255

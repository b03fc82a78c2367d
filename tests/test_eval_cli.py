"""dadiff-eval end to end on a tiny generated benchmark: run (resumable), score, plots, baselines, errors."""

from __future__ import annotations

import json
import shutil
import sys

import numpy as np
import pytest

from dadiff.runtime.commands import eval as eval_cli
from dadiff.runtime.commands.eval import main
from dadiff.runtime.config import TUNABLE_KEYS
from dadiff.runtime.evaluation import evaluate
from dadiff.runtime.evaluation.evaluate import (
    EvalError,
    OpenCVTracker,
    TrackerUnavailable,
    nano_available,
    nano_files,
    nano_problem,
    opencv_available,
    read_result,
    run_record_differences,
)

pytest.importorskip("skimage")  # the scene photos

SIZE = "192x128"


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval") / "bench"
    assert (
        main(
            [
                "generate",
                "--output",
                str(root),
                "--sequences",
                "2",
                "--max-frames",
                "4",
                "--seed",
                "3",
                "--size",
                SIZE,
                "--workers",
                "1",
            ]
        )
        == 0
    )
    return root


@pytest.fixture(scope="module")
def corr_model(tmp_path_factory):
    pytest.importorskip("onnx")
    from runtime_models import write_corr_model

    return write_corr_model(tmp_path_factory.mktemp("model") / "corr")


def _gt(bench, name):
    return np.loadtxt(bench / name / "groundtruth_rect.txt", delimiter=",")


def test_run_writes_pysot_results_and_resumes(bench, corr_model, tmp_path, capsys):
    results = tmp_path / "results"
    args = ["run", "--model", str(corr_model), "--dataset", str(bench), "--output", str(results), "--no-progress"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "corr: tracked 4 sequences" in out and "Succ." in out and "NPrec@0.2" in out
    folder = results / "bench" / "corr"
    boxes = read_result(folder / "seq001_night.txt")
    assert boxes.shape == (4, 4)
    x, y, w, h = _gt(bench, "seq001_night")[0]
    assert boxes[0].tolist() == pytest.approx([x + 0.5, y + 0.5, w, h], abs=1e-3)  # spec 8.5 init box
    states = (folder / "seq001_night.states").read_text().splitlines()
    assert len(states) == 4 and states[0] == "1,init"
    assert all(line.split(",")[1] in ("tracking", "uncertain", "lost") for line in states[1:])
    assert sorted(p.name for p in (results / "plots" / "bench").iterdir()) == [
        "norm_precision_ALL.png",
        "precision_ALL.png",
        "success_ALL.png",
    ]
    (folder / "seq002_day.txt").unlink()
    assert main(args) == 0
    assert "tracked 1 sequence (3 frames" in capsys.readouterr().out  # the other three were kept
    assert main([*args, "--sequences", "*_night", "--attributes", "--no-plots"]) == 0
    out = capsys.readouterr().out
    assert "bench (*_night): 2 sequences" in out and "LAI: 2 sequences" in out


def test_score_json_for_any_result_folder(bench, tmp_path, capsys):
    folder = tmp_path / "mine" / "Perfect"
    folder.mkdir(parents=True)
    for seq in ("seq001_day", "seq001_night", "seq002_day", "seq002_night"):
        np.savetxt(folder / f"{seq}.txt", _gt(bench, seq), delimiter=",")
    assert main(["score", "--dataset", str(bench), "--json", str(tmp_path / "mine")]) == 0
    table = json.loads(capsys.readouterr().out)
    assert list(table) == ["Perfect"]
    assert set(table["Perfect"]) == {"success", "norm_precision", "precision"}
    assert table["Perfect"]["success"] == pytest.approx(20 / 21)
    assert table["Perfect"]["precision"] == 1.0


def test_score_against_prints_the_paired_difference(bench, tmp_path, capsys):
    for name, shift in (("Perfect", 0), ("Shifted", 3)):
        folder = tmp_path / "mine" / name
        folder.mkdir(parents=True)
        for seq in ("seq001_day", "seq001_night", "seq002_day", "seq002_night"):
            gt = _gt(bench, seq)
            gt[1:, 0] += shift  # frame 0 is the init box
            np.savetxt(folder / f"{seq}.txt", gt, delimiter=",")
    assert main(["score", "--dataset", str(bench), "--against", "Perfect", str(tmp_path / "mine")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[-2] == "success minus Perfect (per-sequence bootstrap, 95% interval):"
    assert lines[-1].startswith("  Shifted: -0.") and lines[-1].endswith("over 4 sequences")
    assert main(["score", "--dataset", str(bench), "--against", "Nobody", str(tmp_path / "mine")]) == 2
    assert "--against Nobody: no such tracker among" in capsys.readouterr().err


@pytest.mark.parametrize("kind", ["csrt", "kcf"])
def test_opencv_baselines(bench, tmp_path, capsys, kind):
    if not opencv_available(kind):
        pytest.skip("opencv-contrib is not installed")
    assert main(["run", "--tracker", kind, "--dataset", str(bench), "--output", str(tmp_path), "--no-progress"]) == 0
    assert f"{kind.upper()}: tracked 4 sequences" in capsys.readouterr().out
    assert read_result(tmp_path / "bench" / kind.upper() / "seq002_day.txt").shape == (4, 4)


def test_missing_contrib_is_a_clear_error(monkeypatch):
    import cv2

    monkeypatch.delattr(cv2, "TrackerCSRT", raising=False)
    with pytest.raises(EvalError, match="needs OpenCV's contrib modules"):
        OpenCVTracker("csrt")


def test_an_opencv_tracker_that_raises_is_a_failed_update(monkeypatch):
    """OpenCV's CSRT asserts inside resize on some sequences; that frame is a failure, not a crashed run."""
    import cv2

    class Asserts:
        def init(self, frame, rect):
            pass

        def update(self, frame):
            raise cv2.error("resize: !ssize.empty()")

    monkeypatch.setattr(cv2, "TrackerCSRT", type("TrackerCSRT", (), {"create": staticmethod(Asserts)}),
                        raising=False)
    tracker = OpenCVTracker("csrt")
    frame = np.zeros((64, 64, 3), np.uint8)
    tracker.init(frame, (10.0, 12.0, 8.0, 6.0))
    assert tracker.update(frame) == ((10.0, 12.0, 8.0, 6.0), 0.0, "lost")


def test_nano_baseline(bench, tmp_path, capsys):
    if not nano_available():
        pytest.skip(nano_problem())
    assert main(["run", "--tracker", "nano", "--dataset", str(bench), "--output", str(tmp_path), "--no-progress",
                 "--no-plots"]) == 0
    assert "NANO: tracked 4 sequences" in capsys.readouterr().out
    boxes = read_result(tmp_path / "bench" / "NANO" / "seq001_night.txt")
    assert boxes.shape == (4, 4) and np.all(boxes[:, 2:] > 0)


def test_nano_without_weights_is_one_line_exit_2(bench, tmp_path, capsys):
    empty = tmp_path / "no-weights"
    empty.mkdir()
    args = ["run", "--tracker", "nano", "--nano-dir", str(empty), "--dataset", str(bench), "--output",
            str(tmp_path), "--no-progress"]
    assert main(args) == 2
    line = _one_error_line(capsys)
    assert "nanotrack_backbone_sim.onnx and nanotrack_head_sim.onnx" in line and str(empty) in line
    assert line.startswith("dadiff-eval: error: --tracker nano needs") and "--nano-dir DIR or DADIFF_NANO_DIR" in line
    assert main(["run", "--tracker", "csrt", "--nano-dir", str(empty), "--dataset", str(bench), "--output",
                 str(tmp_path), "--no-progress"]) == 2
    assert "--nano-dir does not apply" in _one_error_line(capsys)


def test_run_takes_tracker_settings(corr_model, bench, tmp_path, capsys):
    """`--hp` reaches the evaluated tracker; a wrong key or a baseline tracker is one line and exit 2."""
    from dadiff.runtime.commands.eval import _make_tracker, build_parser

    args = build_parser().parse_args(["run", "--model", str(corr_model), "--dataset", str(bench), "--output",
                                      str(tmp_path), "--hp", "motion_compensation=0,lost_frames=5"])
    params = _make_tracker(args)[0].tracker.params
    assert (params.motion_compensation, params.lost_frames) == (0.0, 5)
    base = ["run", "--dataset", str(bench), "--output", str(tmp_path), "--no-progress"]
    assert main([*base, "--model", str(corr_model), "--hp", "foo=1"]) == 2
    assert "unknown override 'foo'" in _one_error_line(capsys)
    assert main([*base, "--tracker", "csrt", "--hp", "lost_frames=5"]) == 2
    assert "--hp does not apply to --tracker csrt" in _one_error_line(capsys)


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_bad_input_gives_one_line_and_exit_2(bench, tmp_path, capsys):
    assert main(["score", "--dataset", str(tmp_path / "nope"), str(tmp_path)]) == 2
    assert "no such dataset folder" in _one_error_line(capsys)
    (tmp_path / "empty").mkdir()
    assert main(["score", "--dataset", str(bench), str(tmp_path / "empty")]) == 2
    assert "no result files for bench" in _one_error_line(capsys)
    short = tmp_path / "short" / "T"
    short.mkdir(parents=True)
    for seq in ("seq001_day", "seq001_night", "seq002_day", "seq002_night"):
        (short / f"{seq}.txt").write_text("1,2,3,4\n")
    assert main(["score", "--dataset", str(bench), str(short)]) == 2
    assert "1 box, but seq001_day has 4 ground-truth frames" in _one_error_line(capsys)  # was "1 boxes"
    assert main(["generate", "--output", str(bench), "--sequences", "1"]) == 2
    assert "not an empty folder" in _one_error_line(capsys)


def test_run_without_a_model_explains_that_none_ships(bench, tmp_path, capsys, no_shipped_model):
    assert main(["run", "--dataset", str(bench), "--output", str(tmp_path), "--no-progress"]) == 2
    assert "no trained default model" in _one_error_line(capsys)


def test_sequence_filter_does_not_swallow_result_folders(bench, tmp_path, capsys):
    results = tmp_path / "results"
    assert main(["run", "--dataset", str(bench), "--output", str(results), "--tracker", "dadiff",
                 "--model", "dadiff-mobile", "--no-progress", "--no-plots"]) == 0
    capsys.readouterr()
    folder = results / bench.name
    assert main(["score", "--dataset", str(bench), "--sequences", "*_night", "--sequences", "*_day",
                 str(folder)]) == 0
    assert "4 sequences" in capsys.readouterr().out


def _status(argv: list[str]) -> int:
    """main's exit status, usage errors (which leave through argparse's SystemExit) included."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


@pytest.mark.parametrize("name", ["../../evil", "", ".", "..", "a/b"])
def test_run_name_must_be_one_folder_name(bench, tmp_path, capsys, name):
    results = tmp_path / "deep" / "results"
    assert _status(["run", "--dataset", str(bench), "--output", str(results), "--tracker", "dadiff",
                    "--model", "dadiff-mobile", "--name", name, "--no-progress", "--no-plots"]) == 2
    assert "argument --name: expected a folder name" in _one_error_line(capsys)
    assert list(tmp_path.rglob("*")) == []  # was: ../../evil beside the results, "" the model's name


def test_run_and_score_outputs_never_land_in_the_dataset(bench, tmp_path, capsys):
    before = {p: p.read_bytes() for p in bench.rglob("*") if p.is_file()}
    run = ["run", "--dataset", str(bench), "--tracker", "dadiff", "--model", "dadiff-mobile", "--no-progress"]
    assert main([*run, "--output", str(bench.parent), "--no-plots"]) == 2  # <results>/bench/<name> is in bench
    assert "--output lies inside the input folder" in _one_error_line(capsys)
    assert main([*run, "--output", str(tmp_path / "r"), "--plots", str(bench / "seq001_day" / "img")]) == 2
    assert "--plots lies inside the input folder" in _one_error_line(capsys)
    video = tmp_path / "v.mp4"
    video.write_bytes(b"not results")
    assert main([*run, "--output", str(video), "--no-plots"]) == 2  # was: every sequence tracked, then an error
    assert "v.mp4: is a file, not a folder; --output needs a folder" in _one_error_line(capsys)
    assert main(["score", "--dataset", str(bench), "--plots", str(bench / "plots"), str(tmp_path)]) == 2
    assert "--plots lies inside the input folder" in _one_error_line(capsys)
    assert {p: p.read_bytes() for p in bench.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "r").exists() and video.read_bytes() == b"not results"


@pytest.mark.parametrize(
    ("option", "message"),
    [(["--seed", "-1"], "argument --seed: expected an integer of at least 0, got '-1'"),
     (["--size", "100000x100000"], "argument --size: frame size must be at most 4096 x 4096"),
     (["--size", "16x16"], "argument --size: frame size must be at least 64 x 64")],
)
def test_generate_checks_seed_and_size_before_making_the_folder(tmp_path, capsys, option, message):
    out = tmp_path / "g"
    assert _status(["generate", "--output", str(out), "--sequences", "1", "--max-frames", "3", *option]) == 2
    assert message in _one_error_line(capsys)
    assert not out.exists()  # was: a traceback (numpy's seed, OpenCV's allocation) and an empty folder


def test_score_names_a_deeply_nested_json_dataset(tmp_path, capsys):
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100000 + "]" * 100000)
    assert main(["score", "--dataset", str(deep), str(tmp_path)]) == 2
    assert "deep.json: not a pysot-toolkit JSON file (nested too deeply)" in _one_error_line(capsys)


@pytest.mark.filterwarnings("error::RuntimeWarning")  # pytest keeps warnings off capsys: make one fail the test
def test_score_of_huge_boxes_prints_no_numpy_warning(bench, tmp_path, capsys):
    folder = tmp_path / "T"
    folder.mkdir()
    for seq in ("seq001_day", "seq001_night", "seq002_day", "seq002_night"):
        (folder / f"{seq}.txt").write_text("1e308,1e308,1e308,1e308\n" * 4)
    assert main(["score", "--dataset", str(bench), "--json", str(folder)]) == 0
    captured = capsys.readouterr()
    assert captured.err == "" and json.loads(captured.out)["T"]["success"] == 0


def _weights(folder):
    folder.mkdir(parents=True)
    for name in evaluate.NANO_FILES:
        (folder / name).write_bytes(b"weights")
    return folder


def test_nano_dir_default_is_the_environment_then_the_checkout(tmp_path, monkeypatch):
    """The default used to be ../shared beside the package's folder: after `pip install .`, site-packages/shared.
    Now $DADIFF_NANO_DIR first, then the checkout's ../shared only where it exists; the error says how to give it."""
    env, beside = _weights(tmp_path / "env"), _weights(tmp_path / "checkout-shared")
    monkeypatch.setattr(evaluate, "CHECKOUT_NANO_DIR", beside)
    monkeypatch.setenv("DADIFF_NANO_DIR", str(env))
    assert nano_files()[0] == env / "nanotrack_backbone_sim.onnx"
    assert nano_files(beside)[1] == beside / "nanotrack_head_sim.onnx"  # --nano-dir wins
    monkeypatch.delenv("DADIFF_NANO_DIR")
    assert nano_files()[0].parent == beside
    monkeypatch.setattr(evaluate, "CHECKOUT_NANO_DIR", tmp_path / "site-packages" / "shared")  # installed: none
    with pytest.raises(TrackerUnavailable) as caught:
        nano_files()
    message = str(caught.value)
    assert message.startswith("--tracker nano needs NanoTrack v2's nanotrack_backbone_sim.onnx and "
                              "nanotrack_head_sim.onnx, found nowhere")
    assert message.endswith("give the folder that holds them with --nano-dir DIR or DADIFF_NANO_DIR=DIR")
    assert "site-packages" not in message
    monkeypatch.setenv("DADIFF_NANO_DIR", str(tmp_path / "nope"))
    with pytest.raises(TrackerUnavailable, match=r"not found in .*nope \(from DADIFF_NANO_DIR\)"):
        nano_files()


def _run(bench, results, *extra):
    return ["run", "--dataset", str(bench), "--output", str(results), "--no-plots", "--no-progress", *extra]


def test_run_record_lets_the_same_settings_resume(bench, corr_model, tmp_path, capsys):
    results = tmp_path / "r"
    assert main(_run(bench, results, "--model", str(corr_model), "--hp", "lr=.3")) == 0
    record = json.loads((results / "bench" / "corr" / "run.json").read_text())
    assert record["tracker"] == "dadiff" and record["hp"]["lr"] == 0.3 and "preset" not in record
    assert set(record["hp"]) == set(TUNABLE_KEYS)  # every setting in effect, not only the keys typed
    assert record["model"]["folder"] == str(corr_model.resolve()) and len(record["model"]["search_sha256"]) == 64
    capsys.readouterr()
    copy = shutil.copytree(corr_model, tmp_path / "elsewhere" / "corr")  # the same files elsewhere: same boxes
    assert main(_run(bench, results, "--model", str(copy), "--hp", "lr=0.3", "--threads", "1")) == 0
    captured = capsys.readouterr()
    assert "tracked 0 sequences (0 frames), 4 already done" in captured.out and captured.err == ""


def test_run_into_a_folder_of_other_settings_is_refused(bench, corr_model, tmp_path, capsys):
    """A resumed run skipped every finished sequence and reported the old setting's scores as the new one's."""
    results = tmp_path / "r"
    assert main(_run(bench, results, "--model", str(corr_model))) == 0
    capsys.readouterr()
    folder = results / "bench" / "corr"
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    assert main(_run(bench, results, "--model", str(corr_model), "--hp", "lr=0.05")) == 2
    line = _one_error_line(capsys)
    assert line == (f"dadiff-eval: error: {folder} holds results of other settings (--hp lr: 0.473 before, "
                    "0.05 now): give --name NEW (or another --output) for these settings; nothing tracked")
    assert main(_run(bench, results, "--model", str(corr_model), "--preset", "NUT_L")) == 2
    assert "(--hp window_influence: 0.401 before, 0.403 now)" in _one_error_line(capsys)
    other = write_other_model(tmp_path / "other" / "corr")
    assert main(_run(bench, results, "--model", str(other))) == 2
    line = _one_error_line(capsys)
    assert f"(--model: {corr_model.resolve()} (sha256 " in line and f"before, {other.resolve()} (sha256 " in line
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before  # nothing tracked, nothing rewritten
    assert main(_run(bench, results, "--model", str(corr_model), "--hp", "lr=0.05", "--name", "corr-lr")) == 0
    assert "corr-lr: tracked 4 sequences" in capsys.readouterr().out


def test_the_same_settings_by_another_route_resume(bench, corr_model, tmp_path, capsys):
    """The record held --preset's name and the --hp keys typed: no --preset, then the model's default preset
    by name, or --hp lr at the preset's own value, were refused as other settings though no box changes."""
    results = tmp_path / "r"
    assert main(_run(bench, results, "--model", str(corr_model))) == 0
    capsys.readouterr()
    for extra in (["--preset", "UAVDark70"], ["--hp", "lr=0.473"], ["--preset", "UAVDark70", "--hp", "lr=.473"]):
        assert main(_run(bench, results, "--model", str(corr_model), *extra)) == 0, extra
        captured = capsys.readouterr()
        assert "tracked 0 sequences (0 frames), 4 already done" in captured.out and captured.err == ""


def test_a_folder_with_only_a_run_record_takes_the_new_settings(bench, corr_model, tmp_path, capsys):
    """A run that failed before its first sequence left only run.json; a corrected run with other settings
    was refused as 'holds results of other settings' though there were none."""
    results = tmp_path / "r"
    folder = results / "bench" / "corr"
    folder.mkdir(parents=True)
    (folder / "run.json").write_text(json.dumps({"record": 1, "tracker": "dadiff", "hp": {"lr": 0.9}}))
    assert main(_run(bench, results, "--model", str(corr_model), "--hp", "lr=0.05")) == 0
    assert "corr: tracked 4 sequences" in capsys.readouterr().out
    assert json.loads((folder / "run.json").read_text())["hp"]["lr"] == 0.05


def write_other_model(folder):
    pytest.importorskip("onnx")
    from runtime_models import write_corr_model

    return write_corr_model(folder, gain=9.0)


def test_a_folder_without_a_run_record_still_resumes(bench, corr_model, tmp_path, capsys):
    """Folders of older versions have no run.json: resumed, with one warning, and no record made up for them."""
    results = tmp_path / "r"
    assert main(_run(bench, results, "--model", str(corr_model))) == 0
    record = results / "bench" / "corr" / "run.json"
    record.unlink()
    capsys.readouterr()
    assert main(_run(bench, results, "--model", str(corr_model), "--hp", "lr=0.05")) == 0
    captured = capsys.readouterr()
    assert "tracked 0 sequences (0 frames), 4 already done" in captured.out
    assert _lines(captured.err) == [f"dadiff-eval: warning: {record.parent} has results but no run.json (written "
                                    "by an older dadiff-eval): their settings cannot be checked against this "
                                    "run's; resuming"]
    assert not record.exists()
    record.write_text("{not json")
    assert main(_run(bench, results, "--model", str(corr_model))) == 2
    assert "run.json: unreadable run record" in _one_error_line(capsys)


def _lines(text):
    return text.strip().splitlines()


def test_run_record_differences_compare_files_not_paths():
    model = {"folder": "/a/m", "template_sha256": "t" * 64, "search_sha256": "s" * 64}
    old = {"record": 1, "tracker": "dadiff", "model": model, "preset": None, "hp": {}}
    assert run_record_differences(old, {**old, "model": {**model, "folder": "/b/m"}}) == []
    assert run_record_differences(old, {**old, "preset": "NUT_L"}) == ["--preset: none before, NUT_L now"]
    assert run_record_differences(old, {**old, "model": {**model, "search_sha256": "x" * 64}}) == [
        f"--model: /a/m (sha256 {'s' * 12}) before, /a/m (sha256 {'x' * 12}) now"]
    nano = {"record": 1, "tracker": "nano", "nano": {"folder": "/w", "backbone_sha256": "b" * 64, "head_sha256": "h"}}
    assert run_record_differences(nano, {**nano, "nano": {**nano["nano"], "head_sha256": "g"}})[0].startswith(
        "--nano-dir: /w (sha256 bbbbbbbbbbbb) before")
    assert run_record_differences(old, nano) == ["--tracker: dadiff before, nano now"]


def test_run_draws_its_bar_only_on_a_terminal(bench, corr_model, tmp_path, capsys, monkeypatch):
    """The bar went into logs too (stderr redirected); now only on a terminal, and --no-progress still wins."""
    seen = []
    real = eval_cli.run_tracker

    def spy(*args, progress, **kwargs):
        seen.append(progress)
        return real(*args, progress=progress, **kwargs)

    monkeypatch.setattr(eval_cli, "run_tracker", spy)
    base = ["run", "--dataset", str(bench), "--model", str(corr_model), "--no-plots"]
    assert main([*base, "--output", str(tmp_path / "a")]) == 0
    assert seen == [False] and capsys.readouterr().err == ""  # captured stderr is no terminal: no bar lines
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    assert main([*base, "--output", str(tmp_path / "b")]) == 0
    assert main([*base, "--output", str(tmp_path / "c"), "--no-progress"]) == 0
    assert seen == [False, True, False]


def test_score_against_itself_alone_says_there_is_nothing_to_compare(bench, tmp_path, capsys):
    folder = tmp_path / "mine" / "Perfect"
    folder.mkdir(parents=True)
    for seq in ("seq001_day", "seq001_night", "seq002_day", "seq002_night"):
        np.savetxt(folder / f"{seq}.txt", _gt(bench, seq), delimiter=",")
    assert main(["score", "--dataset", str(bench), "--against", "Perfect", str(folder)]) == 0
    out = capsys.readouterr().out
    assert "success minus" not in out  # was: the heading, then nothing
    assert _lines(out)[-1] == "--against Perfect: nothing to compare (Perfect is the only tracker given)"


def test_score_counts_one_sequence_in_the_singular(bench, tmp_path, capsys):
    folder = tmp_path / "mine" / "Perfect"
    folder.mkdir(parents=True)
    np.savetxt(folder / "seq001_night.txt", _gt(bench, "seq001_night"), delimiter=",")
    assert main(["score", "--dataset", str(bench), "--sequences", "seq001_night", "--attributes", str(folder)]) == 0
    out = capsys.readouterr().out
    assert "bench (seq001_night): 1 sequence\n" in out and "LAI: 1 sequence\n" in out  # was: "1 sequences"
    assert "1 sequences" not in out


def test_generate_without_scikit_image_leaves_no_folder(tmp_path, capsys, monkeypatch):
    """The photos were checked after the --out folder was made: an empty folder stayed behind."""
    from dadiff.runtime.datamaking import photos

    monkeypatch.setitem(sys.modules, "skimage", None)  # `import skimage.data` raises ImportError
    monkeypatch.setitem(sys.modules, "skimage.data", None)
    monkeypatch.setattr(photos, "_photos", photos._photos.__wrapped__)  # past the cache of loaded photos
    out = tmp_path / "g"
    assert main(["generate", "--output", str(out), "--sequences", "1", "--max-frames", "2", "--workers", "1"]) == 2
    assert "need scikit-image's photos, which are not installed here" in _one_error_line(capsys)
    assert not out.exists()


class _Recorder:
    """A tracker that keeps the frames it was given."""

    def __init__(self):
        self.frames = []

    def init(self, frame, gt_box):
        self.frames.append(frame)

    def update(self, frame):
        self.frames.append(frame)
        return (0.0, 0.0, 1.0, 1.0), 1.0, "tracking"


def test_gamma_tracker_lifts_each_frame_before_the_tracker_sees_it():
    inner = _Recorder()
    tracker = evaluate.GammaTracker(inner, 0.5)
    frame = np.array([[[0, 64, 255]]], np.uint8)
    tracker.init(frame, (0, 0, 1, 1))
    tracker.update(frame)
    for seen in inner.frames:  # 255 * (64 / 255) ** 0.5 = 127.75
        assert seen.tolist() == [[[0, 128, 255]]]
    assert frame.tolist() == [[[0, 64, 255]]]  # the caller's frame is left as it was


def test_run_with_gamma_is_its_own_setting_in_run_json(bench, corr_model, tmp_path, capsys):
    results = tmp_path / "r"
    assert main(_run(bench, results, "--model", str(corr_model), "--gamma", "0.5")) == 0
    assert "corr-gamma0.5: tracked 4 sequences" in capsys.readouterr().out
    folder = results / "bench" / "corr-gamma0.5"
    record = json.loads((folder / "run.json").read_text())
    assert record["gamma"] == 0.5 and record["tracker"] == "dadiff" and "search_sha256" in record["model"]
    assert main(_run(bench, results, "--model", str(corr_model), "--name", "corr-gamma0.5")) == 2
    assert "(--gamma: 0.5 before, none now)" in _one_error_line(capsys)
    with pytest.raises(SystemExit) as exit_:
        main(_run(bench, results, "--model", str(corr_model), "--gamma", "0"))
    assert exit_.value.code == 2 and "argument --gamma: expected a number above 0" in _one_error_line(capsys)


def _shifted_results(bench, root, shifts):
    """One result folder per name under `root`, each the truth moved `shift` px right after frame 0."""
    for name, shift in shifts.items():
        folder = root / name
        folder.mkdir(parents=True)
        for seq in ("seq001_day", "seq001_night", "seq002_day", "seq002_night"):
            gt = _gt(bench, seq)
            gt[1:, 0] += shift
            np.savetxt(folder / f"{seq}.txt", gt, delimiter=",")


def test_table_gives_one_markdown_row_per_tracker_with_intervals_and_seed_spread(bench, tmp_path, capsys):
    from dadiff.runtime.datamaking.datasets import load_dataset
    from dadiff.runtime.evaluation.evaluate import score_folder

    results = tmp_path / "results" / "bench"
    _shifted_results(bench, results, {"Perfect": 0, "Shifted": 3, "Model@1": 2, "Model@2": 6})
    sets = ["--set", "night", str(bench), "*_night", str(results), "--set", "day", str(bench), "*_day", str(results)]
    assert main(["table", "--against", "Perfect", *sets]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| tracker | night (*_night) | day (*_day) |" and lines[1] == "|---|---|---|"
    rows = {line.split(" | ")[0][2:]: line for line in lines[2:5]}
    assert list(rows) == ["Perfect", "Model (2 seeds)", "Shifted"]
    assert rows["Perfect"].endswith("| 0.952 / 1.000 (baseline) | 0.952 / 1.000 (baseline) |")
    night = load_dataset(bench).select(["*_night"])
    seeds = [score_folder(night, results / f"Model@{k}").overall.success for k in (1, 2)]
    cell = rows["Model (2 seeds)"].split(" | ")[1]
    assert cell.startswith(f"{np.mean(seeds):.3f} ± {np.std(seeds, ddof=1):.3f} / ")
    difference = float(cell.split("(")[1].split(" ")[0])
    assert difference == pytest.approx(np.mean(seeds) - 20 / 21, abs=5e-4) and difference < 0
    assert "95 % paired bootstrap" in lines[-1]
    assert main(["table", "--against", "Perfect", "--trackers", "Shifted", "Perfect", *sets]) == 0
    assert [line.split(" | ")[0] for line in capsys.readouterr().out.splitlines()[2:4]] == ["| Shifted", "| Perfect"]


def test_table_without_the_baseline_is_one_line_and_exit_2(bench, tmp_path, capsys):
    results = tmp_path / "results" / "bench"
    _shifted_results(bench, results, {"Shifted": 3})
    assert main(["table", "--against", "NANO", "--set", "all", str(bench), "*", str(results)]) == 2
    assert _one_error_line(capsys).startswith("dadiff-eval: error: --against NANO: no such tracker in ")


def test_table_skip_first_scores_the_frames_after_the_init_frame(bench, tmp_path, capsys):
    from dadiff.runtime.evaluation.metrics import success_curve

    results = tmp_path / "results" / "bench"
    _shifted_results(bench, results, {"Perfect": 0, "Shifted": 3})
    args = ["table", "--against", "Perfect", "--set", "night", str(bench), "*_night", str(results)]
    expected = np.mean([success_curve(_gt(bench, s)[1:], _gt(bench, s)[1:] + [3, 0, 0, 0]).mean()
                        for s in ("seq001_night", "seq002_night")])
    for extra, frames in (([], slice(0, None)), (["--skip-first"], slice(1, None))):
        assert main([*args, *extra]) == 0
        out = capsys.readouterr().out
        shifted = [line for line in out.splitlines() if line.startswith("| Shifted |")][0]
        if frames.start:
            assert shifted.startswith(f"| Shifted | {expected:.3f} / ") and "after the init frame" in out
        else:  # with the init frame, whose box is exact for every tracker, the score is higher
            assert float(shifted.split(" | ")[1].split(" ")[0]) > expected + 0.03

"""Model resolution, loading errors, metadata checks, providers."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest

from dadiff import models
from dadiff.runtime import InputError, ModelError, OnnxBackend, Tracker
from dadiff.runtime.config import LOST_DEFAULTS
from dadiff.runtime.onnx_backend import choose_providers
from runtime_models import write_corr_model


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_corr_model(tmp_path_factory.mktemp("good") / "m")


def _variant(tmp_path: Path, **meta: str | None) -> Path:
    return write_corr_model(tmp_path / "variant", meta=meta)


def test_no_default_model_shipped_yet(no_shipped_model) -> None:
    assert models.list_models() == []
    with pytest.raises(models.ModelNotFoundError, match="no trained default model is shipped yet.*--model"):
        models.resolve(None)
    with pytest.raises(ModelError, match="no trained default model is shipped yet"):
        Tracker.load()


def test_resolve_paths(good: Path, tmp_path: Path) -> None:
    assert models.resolve(good) == good
    assert models.resolve(str(good / "template.onnx")) == good
    with pytest.raises(models.ModelNotFoundError, match="model .nope. not found.*shipped: dadiff-mobile"):
        models.resolve("nope")
    text = tmp_path / "notes.txt"
    text.write_text("x")
    with pytest.raises(models.ModelNotFoundError, match="not a model folder or an .onnx file"):
        models.resolve(text)


def test_missing_graph_file(good: Path, tmp_path: Path) -> None:
    folder = tmp_path / "half"
    folder.mkdir()
    shutil.copy(good / "template.onnx", folder)
    with pytest.raises(ModelError, match=r"search\.onnx: file not found"):
        OnnxBackend(folder)


def test_corrupt_file(good: Path, tmp_path: Path) -> None:
    folder = tmp_path / "corrupt"
    shutil.copytree(good, folder)
    (folder / "search.onnx").write_bytes(b"\x08\x07garbage" * 50)
    with pytest.raises(ModelError, match=r"search\.onnx: not a loadable ONNX model") as info:
        OnnxBackend(folder)
    assert "\n" not in str(info.value)


def test_model_without_metadata(tmp_path: Path) -> None:
    from runtime_models import metadata

    folder = _variant(tmp_path, **{key: None for key in metadata("search")})
    with pytest.raises(ModelError, match=r"template\.onnx: metadata key 'dadiff_format' is missing"):
        OnnxBackend(folder)


@pytest.mark.parametrize(
    ("meta", "message"),
    [
        ({"stride": None}, r"template\.onnx: metadata key 'stride' is missing"),
        ({"score_size": "25.5"}, "metadata key 'score_size' is '25.5', expected an integer"),
        ({"dadiff_format": "2"}, "this runtime reads format 1"),
        ({"hp_presets": "{not json"}, "'hp_presets' is not valid JSON"),
        ({"lost_frames": "0"}, "metadata key 'lost_frames' is 0"),
        ({"lr": "1.5"}, r"metadata key 'lr' is 1.5, expected \[0.0, 1.0\]"),
        ({"channel_order": "BRG"}, "expected BGR or RGB"),
        # huge but finite values: each overflowed the crop arithmetic (an OverflowError traceback)
        ({"context_amount": "1e308"}, "metadata key 'context_amount' is '1e308', expected at most 10"),
        ({"min_size": "1e308"}, "metadata key 'min_size' is '1e308', expected at most 1000"),
        ({"point_origin": "1e308"}, "'point_origin' is '1e308', larger than the 255 px search crop"),
        ({"stride": "1e308"}, "'stride' is '1e308', larger than the 255 px search crop"),
        ({"lost_frames": "1e300"}, r"'lost_frames' is 1e\+300, expected \[1, 1000000\]"),  # not 301 digits
        ({"hp_presets": "[" * 100_000 + "]" * 100_000}, r"'hp_presets' is not valid JSON \(nested too deeply\)"),
        (
            {"instance_size": "256"},
            r"search\.onnx: x has shape \[1, 3, 255, 255\], expected \[1, 3, 256, 256\]",
        ),
    ],
)
def test_bad_metadata(tmp_path: Path, meta: dict, message: str) -> None:
    with pytest.raises(ModelError, match=message):
        OnnxBackend(_variant(tmp_path, **meta))


def test_graph_files_must_agree(good: Path, tmp_path: Path) -> None:
    other = _variant(tmp_path, min_size="20")
    shutil.copy(good / "template.onnx", other / "template.onnx")
    with pytest.raises(ModelError, match="disagree on metadata key 'min_size'"):
        OnnxBackend(other)


def test_lost_thresholds_from_metadata(tmp_path: Path) -> None:
    tracker = Tracker(OnnxBackend(_variant(tmp_path, lost_score="0.1", search_growth="1.5"), threads=1))
    assert (tracker.params.lost_score, tracker.params.search_growth) == (0.1, 1.5)
    assert tracker.params.uncertain_score == LOST_DEFAULTS["uncertain_score"]


def test_providers(good: Path) -> None:
    assert choose_providers()[-1] == "CPUExecutionProvider"
    assert choose_providers("cpu") == ["CPUExecutionProvider"]
    assert OnnxBackend(good, provider="CPUExecutionProvider", threads=1).providers == ["CPUExecutionProvider"]
    with pytest.raises(InputError, match="provider 'warp-drive' is not available here"):
        OnnxBackend(good, provider="warp-drive")
    with pytest.raises(InputError, match="threads must be a positive integer"):
        OnnxBackend(good, threads=0)
    with pytest.raises(InputError, match="threads is 100000; at most"):  # was: a hang, or all memory at 1e6
        OnnxBackend(good, threads=100_000)


def test_the_shipped_default_is_a_trained_mobile_model() -> None:
    assert models.DEFAULT_MODEL in models.list_models()
    folder = models.resolve(None)
    assert (folder / "MODEL_CARD.md").is_file()
    tracker = Tracker.load(threads=1)
    assert tracker.backend.meta["family"] == "dadiff-mobile"
    card = (folder / "MODEL_CARD.md").read_text()
    assert "runs/dadiff-mobile/11-people-tracks-more/final-ema.pt" in card  # names its run (the recipe's last stage)
    # the training state the card says it was exported from is committed and is what the graphs came from
    state = "export/resume/mobile-dadiff-tracks-s81-ema-average.pt"
    assert f"`{state}`" in card
    repo = Path(__file__).resolve().parents[1]
    assert hashlib.sha256((repo / state).read_bytes()).hexdigest() == tracker.backend.meta["source_sha256"]

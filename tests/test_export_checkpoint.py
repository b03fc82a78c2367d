"""Checkpoint reading: formats, prefixes, family detection and one-line errors for bad files."""

from __future__ import annotations

import pickle

import pytest

torch = pytest.importorskip("torch")

from dadiff.export.checkpoint import CheckpointError, load_checkpoint  # noqa: E402
from dadiff.export.config import lite_config  # noqa: E402
from dadiff.export.network import build_model  # noqa: E402


@pytest.fixture(scope="module")
def lite_sd() -> dict[str, torch.Tensor]:
    torch.manual_seed(1)
    return build_model(lite_config()).state_dict()


def _one_line_error(path, **kwargs) -> str:
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path, **kwargs)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg
    return msg


def test_bare_state_dict_with_module_prefix_loads(tmp_path, lite_sd):
    path = tmp_path / "bare.pth"
    torch.save({f"module.{k}": v for k, v in lite_sd.items()}, path)
    loaded = load_checkpoint(path)
    assert loaded.config.family == "dadiff-lite"
    for k, v in loaded.model.state_dict().items():
        assert torch.equal(v, lite_sd[k]), k


def test_released_container_format_loads(tmp_path, lite_sd):
    path = tmp_path / "checkpoint_e40.pth"
    torch.save({"epoch": 40, "state_dict": lite_sd, "optimizer": {}}, path)
    assert load_checkpoint(path).config.family == "dadiff-lite"


def test_ban_released_checkpoint_detected_with_prefix(tmp_path, ban_shapes):
    from dadiff.export.procedural import write_released_checkpoint

    path = tmp_path / "released.pth"
    write_released_checkpoint(str(path), ban_shapes, module_prefix=True)
    loaded = load_checkpoint(path)
    assert loaded.config.family == "dadiff-ban-r50" and loaded.source == "released"
    assert not loaded.model.training


def test_missing_unexpected_and_shape_errors_are_named(tmp_path, lite_sd):
    sd = dict(lite_sd)
    del sd["head.cls_weight"]
    sd["head.extra_thing"] = torch.zeros(3)
    sd["neck.downsample0.downsample.0.weight"] = torch.zeros(5, 192, 1, 1)
    path = tmp_path / "bad.pth"
    torch.save(sd, path)
    msg = _one_line_error(path)
    assert "missing 1 key(s): head.cls_weight" in msg
    assert "unexpected 1 key(s): head.extra_thing" in msg
    assert "neck.downsample0.downsample.0.weight [5, 192, 1, 1] vs model [64, 192, 1, 1]" in msg


def test_missing_file_folder_and_empty_file(tmp_path):
    assert "no such file" in _one_line_error(tmp_path / "nope.pth")
    assert "is a folder" in _one_line_error(tmp_path)
    empty = tmp_path / "empty.pth"
    empty.write_bytes(b"")
    assert "empty file" in _one_line_error(empty)


def test_not_a_torch_file(tmp_path):
    path = tmp_path / "notes.pth"
    path.write_text("this is not a checkpoint\n" * 10)
    assert "not a PyTorch checkpoint" in _one_line_error(path)


class Exploit:
    def __reduce__(self):
        return (print, ("pwned",))


def test_pickled_code_is_refused(tmp_path):
    path = tmp_path / "evil.pth"
    torch.save({"state_dict": {"a": torch.zeros(1)}, "payload": Exploit()}, path)
    msg = _one_line_error(path)
    assert "refused" in msg and "weights-only" in msg
    raw = tmp_path / "evil_raw.pth"
    raw.write_bytes(pickle.dumps(Exploit()))
    assert "refused" in _one_line_error(raw) or "not a PyTorch checkpoint" in _one_line_error(raw)


def test_truncated_file(tmp_path, lite_checkpoint):
    data = lite_checkpoint.read_bytes()
    path = tmp_path / "cut.pt"
    path.write_bytes(data[: len(data) // 2])
    assert "truncated or corrupt" in _one_line_error(path)


def test_wrong_family(tmp_path, lite_sd, lite_checkpoint):
    assert "holds a dadiff-lite model, not dadiff-ban-r50" in _one_line_error(lite_checkpoint, family="dadiff-ban-r50")
    siamgat = tmp_path / "siamgat.pth"
    torch.save({"backbone.Mixed_6e.branch1x1.conv.weight": torch.zeros(1),
                "car_head.cls_logits.weight": torch.zeros(2)}, siamgat)
    assert "plain SiamGAT checkpoint without the DaDiff block" in _one_line_error(siamgat)
    siamban = tmp_path / "siamban.pth"
    torch.save({"backbone.layer1.0.conv1.weight": torch.zeros(1)}, siamban)
    assert "without the DaDiff block" in _one_line_error(siamban)


def test_our_format_round_trip_keeps_config_and_steps(tmp_path, lite_checkpoint):
    loaded = load_checkpoint(lite_checkpoint, steps=4)
    assert loaded.config.ddim_steps == 4 and loaded.model.sampler.timesteps == [15, 10, 5, 0]
    assert loaded.model.sampler.start_t == 15

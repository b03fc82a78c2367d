"""EfficientNet-Lite0 backbone: pretrained weights load, classify photos, atrous trunk keeps stride 8."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")
nn = torch.nn

from dadiff.export.efficientnet_lite import (  # noqa: E402
    PIXEL_MEAN,
    PIXEL_STD,
    EfficientNetLite0,
    load_imagenet_weights,
    pretrained_weights_path,
)

skimage_data = pytest.importorskip("skimage.data")

CAT_CLASSES = set(range(281, 286))  # tabby, tiger cat, Persian, Siamese, Egyptian cat
COFFEE_CLASSES = {504, 967}  # coffee mug, espresso


@pytest.fixture(scope="module")
def classifier() -> EfficientNetLite0:
    model = EfficientNetLite0(with_head=True)
    load_imagenet_weights(model)
    return model.eval()


def _bgr_input(rgb: np.ndarray) -> torch.Tensor:
    """skimage gives RGB uint8; the model takes raw BGR 0..255 float32 NCHW like an OpenCV frame."""
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    bgr = cv2.resize(bgr, (224, 224), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(bgr.astype(np.float32)).permute(2, 0, 1).unsqueeze(0)


def _top5(model: nn.Module, rgb: np.ndarray) -> list[int]:
    with torch.no_grad():
        logits = model(_bgr_input(rgb))
    assert logits.shape == (1, 1000)
    return logits[0].topk(5).indices.tolist()


def test_classifies_cat(classifier: EfficientNetLite0) -> None:
    # Measured top-5: 285 Egyptian cat 0.67, 282 tiger cat 0.14, 281 tabby 0.13, 287 lynx, 728 plastic bag.
    top5 = _top5(classifier, skimage_data.chelsea())
    assert top5[0] in CAT_CLASSES, top5
    assert CAT_CLASSES & set(top5), top5


def test_classifies_coffee(classifier: EfficientNetLite0) -> None:
    # Measured top-5: 967 espresso 0.89, 968 cup 0.04, 925 consomme 0.02, 504 coffee mug 0.01, 809 soup bowl.
    top5 = _top5(classifier, skimage_data.coffee())
    assert COFFEE_CLASSES & set(top5), top5


def test_keys_and_shapes_match_pretrained_file() -> None:
    state = torch.load(pretrained_weights_path(), weights_only=True, map_location="cpu")
    own = EfficientNetLite0(with_head=True).state_dict()
    assert set(own) == set(state)
    assert {k: tuple(v.shape) for k, v in own.items()} == {k: tuple(v.shape) for k, v in state.items()}


def test_normalisation_constants() -> None:
    # TF Lite preprocessing, the same for every channel, so BGR vs RGB order does not change the metadata.
    assert PIXEL_MEAN == (127.0, 127.0, 127.0)
    assert PIXEL_STD == (128.0, 128.0, 128.0)


@pytest.mark.parametrize(("size", "feat"), [(255, 32), (127, 16)])
def test_atrous_trunk_output_stride_8(size: int, feat: int) -> None:
    # Symmetric padding: 255 -> stem 128 -> 64 -> 32 (block 5's stride removed): 32x32; 127 -> 64 -> 32 -> 16.
    # Stride 8 both ways: (255 - 127) / 8 == 32 - 16.
    model = EfficientNetLite0(last_block=10, dilate_from_block=5, out_blocks=(7, 10)).eval()
    load_imagenet_weights(model)  # a truncated model takes the subset of keys it has
    assert not any(k.startswith(("_blocks.11.", "_conv_head", "_fc")) for k in model.state_dict())
    with torch.no_grad():
        outs = model(torch.rand(1, 3, size, size) * 255)
    assert [tuple(o.shape) for o in outs] == [(1, 80, feat, feat), (1, 112, feat, feat)]
    assert model._blocks[5]._depthwise_conv.stride == (1, 1)
    assert model._blocks[5]._depthwise_conv.dilation == (2, 2)
    assert model._blocks[4]._depthwise_conv.dilation == (1, 1)


def test_load_rejects_mismatched_shape() -> None:
    model = EfficientNetLite0(with_head=True)
    model._fc = nn.Linear(1280, 10)  # e.g. a 10-class head: must not load silently
    with pytest.raises(ValueError, match=r"_fc\.weight.*\(10, 1280\).*\(1000, 1280\)"):
        load_imagenet_weights(model)


def test_load_rejects_key_missing_from_file(tmp_path) -> None:
    state = torch.load(pretrained_weights_path(), weights_only=True, map_location="cpu")
    del state["_blocks.3._depthwise_conv.weight"]
    path = tmp_path / "partial.pth"
    torch.save(state, path)
    with pytest.raises(ValueError, match=r"missing from the file: _blocks\.3\._depthwise_conv\.weight"):
        load_imagenet_weights(EfficientNetLite0(last_block=4, out_blocks=(4,)), str(path))


def test_folded_normalisation_computes_the_same(classifier: EfficientNetLite0) -> None:
    """The export's fold (std and channel swap in the stem weights) changes no output, borders included."""
    import copy

    folded = copy.deepcopy(classifier)
    folded.fold_normalisation()
    folded.fold_normalisation()  # a second call must not fold twice
    x = torch.randint(0, 256, (1, 3, 131, 131)).float()  # odd size: the stride-2 stem pads both sides
    with torch.no_grad():
        before, after = classifier(x), folded(x)
        stem_before = classifier._conv_stem(classifier.normalize(x))
        stem_after = folded._conv_stem(folded.normalize(x))
    assert folded.folded and not classifier.folded
    assert (stem_after - stem_before).abs().max().item() < 1e-4
    assert (after - before).abs().max().item() < 1e-3
    assert not torch.equal(folded._conv_stem.weight, classifier._conv_stem.weight)

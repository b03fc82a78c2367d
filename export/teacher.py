"""A reference tracker as a training teacher: NanoTrack v3 (ONNX, onnxruntime) run on our training crops.

NanoTrack was trained on large labelled video data that cannot be had here; its features and responses
carry that knowledge into our own network by distillation. Only its outputs are used, as targets during
training: none of its tensors enter our checkpoints or exported models (see ../shared/weights/README.md).

Its backbone graph is fixed at 255 x 255, so a 127 template crop is pasted in the middle of a mean-colour
255 canvas and the centre 8 x 8 cells are kept (the map is translation-equivariant away from its borders).
Its 15 x 15 score map shares our stride (16) and centring, so our 13 x 13 map is its inner 13 x 13.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from dadiff.runtime.errors import DadiffError

BACKBONE, HEAD = "nanotrack_backbone.onnx", "nanotrack_head.onnx"
TEACHER_SIZE, TEACHER_SCORE, TEACHER_STRIDE = 255, 15, 16


class TeacherError(DadiffError, ValueError):
    """Missing or unusable teacher files (one-line message)."""


class NanoTrackTeacher:
    """Search features (B, 96, 16, 16), foreground probability (B, S, S) and box distances (B, 4, S, S) for
    batches of raw BGR crops, cropped to a student score map of side S (odd, <= 15)."""

    def __init__(self, folder: str | Path, threads: int = 1) -> None:
        folder = Path(folder).expanduser()
        missing = [name for name in (BACKBONE, HEAD) if not (folder / name).is_file()]
        if missing:
            raise TeacherError(f"{folder}: teacher files missing: {', '.join(missing)} (NanoTrack v3 ONNX)")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.log_severity_level = 3
        self.backbone = ort.InferenceSession(str(folder / BACKBONE), opts, providers=["CPUExecutionProvider"])
        self.head = ort.InferenceSession(str(folder / HEAD), opts, providers=["CPUExecutionProvider"])

    def _features(self, crop: np.ndarray) -> np.ndarray:
        return self.backbone.run(None, {"input": crop[None]})[0][0]

    def template_features(self, z: np.ndarray) -> np.ndarray:
        """(3, h, w) template crop (h, w <= 255) -> (96, 8, 8) features of its centre."""
        canvas = np.empty((3, TEACHER_SIZE, TEACHER_SIZE), np.float32)
        canvas[:] = z.mean(axis=(1, 2), keepdims=True)
        h, w = z.shape[1:]
        top, left = (TEACHER_SIZE - h) // 2, (TEACHER_SIZE - w) // 2
        canvas[:, top:top + h, left:left + w] = z
        return self._features(canvas)[:, 4:12, 4:12]

    @torch.no_grad()
    def __call__(self, z: torch.Tensor, x: torch.Tensor,
                 score_size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if x.shape[-2:] != (TEACHER_SIZE, TEACHER_SIZE):
            raise TeacherError(f"the teacher needs {TEACHER_SIZE} x {TEACHER_SIZE} search crops, got {tuple(x.shape)}")
        if score_size % 2 == 0 or score_size > TEACHER_SCORE:
            raise TeacherError(f"the student's score map must be odd and at most {TEACHER_SCORE}, got {score_size}")
        m = (TEACHER_SCORE - score_size) // 2
        feats, probs, locs = [], [], []
        for zi, xi in zip(z.numpy(), x.numpy(), strict=True):
            xf = self._features(np.ascontiguousarray(xi))
            cls, loc = self.head.run(None, {"input1": self.template_features(zi)[None], "input2": xf[None]})
            e = np.exp(cls[0] - cls[0].max(axis=0, keepdims=True))
            probs.append((e[1] / e.sum(axis=0))[m:m + score_size, m:m + score_size])
            locs.append(loc[0][:, m:m + score_size, m:m + score_size])
            feats.append(xf)
        return (torch.from_numpy(np.stack(feats)), torch.from_numpy(np.stack(probs)),
                torch.from_numpy(np.stack(locs)))


"""`dadiff-train` entry point: arguments and the config keys, checked before torch loads.

`--help` and usage errors stay fast (importing torch takes seconds), and a companion computer without the
`export` extra gets one line naming what to install instead of a ModuleNotFoundError.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dadiff.runtime.argtypes import add_renamed, float_in, int_in
from dadiff.runtime.errors import OneLineParser

PROG = "dadiff-train"
SEED_MAX = 2**32 - 1  # numpy's legacy generators take no more; seed * 1000 + rank must fit torch's 64 bits
EXPORT_EXTRA = 'pip install "dadiff[export]"'

# key, default, what it does: the TrainConfig fields (tests/test_reliability_export.py keeps them in step)
CONFIG_KEYS: tuple[tuple[str, str, str], ...] = (
    ("out", '"runs/lite"', "output folder: last.pt (resume), final.pt (export this), log.csv"),
    ("stage", '"dadiff"', '"baseline" (tracker alone, day pairs) or "dadiff" (with the DaDiff block)'),
    ("family", '"dadiff-lite"', "dadiff-lite, dadiff-mobile or dadiff-ban-r50"),
    ("init", '"imagenet"', '"imagenet" or a dadiff checkpoint to start from (e.g. the baseline\'s final.pt)'),
    ("model", "{}", "model config overrides, e.g. {align = \"none\", ddim_steps = 4}"),
    ("day", '[{kind = "scenes", split = "train"}]', "day data: kind scenes, got10k, otb, sequences or images"),
    ("night", "(rendered)", "folder of night images or videos; default: the day frames rendered at night"),
    ("night_styles", '["real"]', "night renderer styles, one drawn per pair: real, classic, camera"),
    ("night_pairs", '"frame"', '"frame" (a night per frame) or "scene": one night over a generated scene\'s pair'),
    ("night_path_lamps", "0.0", 'share of "scene" night pairs given 1-3 lamp heads beside the target (0-1)'),
    ("negative_pairs", "0.0", "share of pairs whose search crop holds another object, negative there (0-1)"),
    ("steps", "1000", "training steps (>= 1)"),
    ("batch_size", "16", "pairs per step and process (>= 2)"),
    ("workers", "0", "data loader processes"),
    ("optimizer", '"sgd"', '"sgd" (the release) or "adamw"'),
    ("lr", "0.0015", "base learning rate (> 0)"),
    ("backbone_lr_mult", "0.1", "backbone learning-rate factor"),
    ("dadiff_lr_mult", "1.0", "learning-rate factor of the DaDiff block (denoiser, aligned layer, gate)"),
    ("warmup_steps", "50", "linear warm-up steps"),
    ("weight_decay", "0.0001", "weight decay"),
    ("freeze_backbone_blocks", "5", "EfficientNet-Lite0 blocks 0..N-1 kept at ImageNet"),
    ("disc_lr", "0.005", "discriminator learning rate (paper: 0.005)"),
    ("disc_poly_power", "0.8", "discriminator poly decay power"),
    ("lambda_trc", "1.0", "tracking loss weight"),
    ("lambda_loc", "1.0", "box (IoU) loss weight within the tracking loss, day and night"),
    ("lambda_adv", "0.1", "adversarial loss weight"),
    ("lambda_align", "1.0", "alignment loss weight"),
    ("adversarial", "true", "ablation switch: the adversarial loss"),
    ("align_loss", "true", "ablation switch: the alignment loss"),
    ("block", "true", "false: dadiff stage without the DaDiff block, the adversary judging the neck features"),
    ("align_target", '"eps"', '"eps" (paper eq. 6), "chain": sampler output on night vs on the paired day frame, '
     '"restore": aligned night features vs the paired day neck features'),
    ("search_scale", "0.18", "search crops rescaled by exp(U(-s, s)) around the target (0-1)"),
    ("search_shift", "64.0", "search crops moved U(-s, s) crop px each way off the target (0-128): how far "
     "a target may jump"),
    ("loc_region", '"ellipse"', 'box regressed at BAN\'s positive "ellipse" or at every point in the "box"'),
    ("lambda_side", "0.0", "each box side's own log error (floor 4 crop px) beside the IoU loss, within the box loss"),
    ("grad_clip", "10.0", "gradient norm clip (> 0)"),
    ("train_only", "[]", 'parameter-name prefixes to train, the rest frozen, e.g. ["head.box0.loc."]'),
    ("checkpoint_every", "100", "steps between last.pt saves (>= 1)"),
    ("keep_checkpoints", "false", "also keep each of those saves as step-NNNNNN.pt (to choose one by tracking)"),
    ("ema_decay", "0.0", "> 0 (below 1): also keep a moving average of the weights, saved as final-ema.pt"),
    ("seed", "0", f"random seed (0..{SEED_MAX})"),
    ("teacher", "(none)", "NanoTrack v3 ONNX folder to distil from (stride-16 families)"),
    ("lambda_distill", "1.0", "teacher response distillation weight"),
    ("lambda_feature", "0.5", "teacher search-feature distillation weight"),
    ("lambda_night_distill", "0.0", "the teacher's day-crop responses as targets on the rendered night crops"),
    ("lambda_night_trc", "0.0", "tracking loss on the rendered night pairs too (their boxes are the day boxes)"),
)
# not a TrainConfig field: export/train_toml.py follows it before the keys are read
EXTENDS = ("extends", "(none)", "a config (path relative to this file) to start from; each key here replaces its value")
# not a TrainConfig field either: export/train_stages.py reads the stage list
STAGES = ("[[stages]]", "(none)", "a recipe in stages run in order in <out>/NN-name, each from the previous one's "
          "final state: name, resume = true (go on with its run), stop_at = N, and the keys the stage changes")


def config_help() -> str:
    rows = "\n".join(f"  {key:<23} {default:<38} {what}"
                     for key, default, what in (*CONFIG_KEYS, EXTENDS, STAGES))
    return ("config keys (top level, or inside [train], [loss], [data], [output] tables; types are checked):\n"
            f"{rows}\n\nFinished runs write <out>/final.pt: export it with dadiff-export <out>/final.pt. "
            f"Exit codes: 0 done or stopped by --max-steps/--max-minutes (resume with the same command), 2 bad "
            f"input (one '{PROG}: error:' line), 130 interrupted.")


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog=PROG, description="The paper's two-stage training, resumable, single process or "
                      "torchrun (needs the export extra: torch).", epilog=config_help(),
                      formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True,
                   help="training config (TOML); examples in the checkout's export/configs/ (installed: "
                        "dadiff/export/configs/ in site-packages)")
    p.add_argument("--max-steps", type=int_in(1),
                   help="stop after this many steps of this run (resume later; default: run to 'steps')")
    add_renamed(p, "-o", "--output", former=["--out"], help="override the config's output folder (its 'out' key)")
    p.add_argument("--seed", type=int_in(0, SEED_MAX),
                   help="override the config's seed (a second run of one recipe: use another --output too)")
    p.add_argument("--show-config", action="store_true",
                   help="print the config the run would use (after 'extends' and --output/--seed) and exit")
    p.add_argument("--device", default="cpu", help="cpu, cuda or auto (default: %(default)s)")
    p.add_argument("--max-minutes", type=float_in(0, open_low=True),
                   help="stop after this many minutes of this run (resume later; default: no limit)")
    return p


def finish_line(step: int, steps: int, out: Path, averaged: bool = False) -> str:
    """What the run leaves: final.pt (and its weight average) to export when done, last.pt to resume from."""
    if step >= steps:
        also = f" (the weight average: {out / 'final-ema.pt'})" if averaged else ""
        return f"step {step}/{steps}; done: export {out / 'final.pt'}{also} with dadiff-export"
    return f"stopped at step {step}/{steps}; resume with the same command (state in {out / 'last.pt'})"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)  # --help and usage errors before torch loads
    try:
        from . import train
    except ModuleNotFoundError as e:
        print(f"{PROG}: error: training needs PyTorch, which is not installed here (no module {e.name!r}): "
              f"{EXPORT_EXTRA}", file=sys.stderr)
        return 2
    return train.main(args)


if __name__ == "__main__":
    sys.exit(main())

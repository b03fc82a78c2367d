"""`dadiff-export checkpoint.pt`: checkpoint -> parity-checked ONNX model folder (docs/model-format.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .checkpoint import CheckpointError, load_checkpoint
from .config import FAMILIES, HP_PRESETS
from .onnx_export import DEFAULT_OPSET, PARITY_TOLERANCE, SUPPORTED_OPSETS, ExportError, export_model


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dadiff-export", description=__doc__)
    p.add_argument("checkpoint", help="released DaDiff-BAN checkpoint (.pth) or a dadiff checkpoint (.pt)")
    p.add_argument("-o", "--output", help="output model folder (default: ./<name>)")
    p.add_argument("--name", help="model name stored in the metadata (default: the checkpoint's file stem)")
    p.add_argument("--steps", type=int, help="DDIM steps K to unroll (default: the checkpoint's, 2)")
    p.add_argument("--opset", type=int, default=DEFAULT_OPSET,
                   help=f"ONNX opset, {SUPPORTED_OPSETS.start}..{SUPPORTED_OPSETS.stop - 1} (default {DEFAULT_OPSET})")
    p.add_argument("--family", choices=FAMILIES, help="require this model family")
    p.add_argument("--preset", choices=sorted(HP_PRESETS),
                   help="hyper-parameter preset the runtime uses by default (default: the checkpoint's)")
    p.add_argument("--tolerance", type=float, default=PARITY_TOLERANCE,
                   help=f"max-abs torch/onnxruntime difference allowed (default {PARITY_TOLERANCE:g})")
    return p


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.opset not in SUPPORTED_OPSETS:
        parser.error(f"unsupported opset {args.opset}; use {SUPPORTED_OPSETS.start}..{SUPPORTED_OPSETS.stop - 1}")
    if args.steps is not None and not 1 <= args.steps <= 20:
        parser.error(f"--steps must be in 1..20, got {args.steps}")
    name = args.name or Path(args.checkpoint).stem
    out = Path(args.output) if args.output else Path(name)
    try:
        loaded = load_checkpoint(args.checkpoint, family=args.family, steps=args.steps, preset=args.preset)
        print(f"dadiff-export: {args.checkpoint}: {loaded.config.family} ({loaded.source} format, "
              f"sha256 {loaded.sha256[:12]}…)", flush=True)
        report = export_model(loaded, out, name, args.opset, args.tolerance)
    except CheckpointError as e:
        print(f"dadiff-export: error: {e}", file=sys.stderr)
        return 2
    except ExportError as e:
        print(f"dadiff-export: error: {e}", file=sys.stderr)
        return 1 if "parity" in str(e) else 2
    sampler = loaded.model.sampler
    files = ", ".join(f"{f} {_mb(n)}" for f, n in report.files.items())
    parity = ", ".join(f"{k} {v:.1e}" for k, v in report.parity_abs.items())
    print(f"  wrote {out}/: {files}")
    print(f"  GFLOP per search frame {report.gflop_search:.2f}, template (once) {report.gflop_template:.2f}; "
          f"DDIM {len(sampler.timesteps)} steps, timesteps {sampler.timesteps}, start t {sampler.start_t}")
    print(f"  parity torch vs onnxruntime (max-abs, relative where |output| > 1): {report.max_parity:.1e} "
          f"(tolerance {args.tolerance:g}) OK; max-abs per output [{parity}]")
    print(f"  export time {report.seconds:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

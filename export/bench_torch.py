"""The PyTorch side of `dadiff-bench`, run as a subprocess so the onboard runtime never imports torch.

`python -m dadiff.export.bench_torch search CKPT CROPS.npz --steps K --threads N`: seconds per eager
search-graph call on the exact crops the ONNX benchmark used (the same graph the export traces).
`python -m dadiff.export.bench_torch peak --threads N`: this CPU's arithmetic limit, measured as the
GFLOP/s of onnxruntime's best kernel (a large dense 3x3 convolution, NCHWc layout). Both print JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import TensorProto, helper, numpy_helper

from .checkpoint import load_checkpoint
from .onnx_export import GraphLayout, SearchGraph, TemplateGraph


def torch_search_times(checkpoint: str, crops: str, steps: int | None, threads: int, repeats: int = 3) -> list[float]:
    torch.set_num_threads(threads)
    loaded = load_checkpoint(checkpoint, steps=steps)
    net = loaded.model.eval()
    data = np.load(crops)
    with torch.inference_mode():
        template = [torch.from_numpy(data[k]) for k in ("z", "roi") if k in data]  # roi: DaDiff-GAT's
        kernels = GraphLayout.of(net).search_args(TemplateGraph(net)(*template))
        search = SearchGraph(net)
        xs = torch.from_numpy(data["xs"])
        search(xs[:1], *kernels)
        times = []
        for _ in range(repeats):
            for x in xs:
                start = time.perf_counter()
                search(x[None], *kernels)
                times.append(time.perf_counter() - start)
    return times


def conv_peak_gflops(threads: int, channels: int = 256, size: int = 64, runs: int = 20) -> float:
    """Best GFLOP/s of one dense 3x3 convolution with constant weights (what MLAS runs fastest)."""
    rng = np.random.default_rng(0)
    weight = numpy_helper.from_array(rng.standard_normal((channels, channels, 3, 3)).astype(np.float32), "w")
    graph = helper.make_graph(
        [helper.make_node("Conv", ["x", "w"], ["y"], pads=[1, 1, 1, 1])], "peak",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, channels, size, size])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)], [weight])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 9
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    x = rng.standard_normal((1, channels, size, size)).astype(np.float32)
    session.run(None, {"x": x})
    best = min(_timed(session, x) for _ in range(runs))
    return 2 * channels * channels * 9 * size * size / best / 1e9


def _timed(session: ort.InferenceSession, x: np.ndarray) -> float:
    start = time.perf_counter()
    session.run(None, {"x": x})
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dadiff.export.bench_torch", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    search = sub.add_parser("search")
    search.add_argument("checkpoint")
    search.add_argument("crops")
    search.add_argument("--steps", type=int)
    search.add_argument("--threads", type=int, default=1)
    search.add_argument("--repeats", type=int, default=3)
    peak = sub.add_parser("peak")
    peak.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    if args.command == "search":
        times = torch_search_times(args.checkpoint, args.crops, args.steps, args.threads, args.repeats)
        print(json.dumps({"torch": torch.__version__, "times": times}))
    else:
        print(json.dumps({"onnxruntime": ort.__version__, "onnx": onnx.__version__,
                          "gflops": conv_peak_gflops(args.threads)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

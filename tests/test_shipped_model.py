"""The shipped models: no random ops, the informational metadata, and the checkpoint shipped beside them."""

from __future__ import annotations

import numpy as np
import onnx
import pytest

from dadiff import models


def _shipped() -> list:
    return [models.resolve(name) for name in models.list_models()]


@pytest.mark.parametrize("folder", _shipped(), ids=lambda p: p.name)
def test_graphs_are_deterministic_and_describe_their_cost(folder) -> None:
    for graph in ("template", "search"):
        model = onnx.load(str(folder / f"{graph}.onnx"))
        assert not [n.op_type for n in model.graph.node if n.op_type.startswith("Random")]
        meta = {p.key: p.value for p in model.metadata_props}
        assert float(meta["gflop_search"]) > 0 and float(meta["gflop_template"]) > 0


def test_default_checkpoint_reproduces_the_shipped_graphs() -> None:
    """checkpoint.pt is what --compare-torch and --sweep-steps start from: it must be the shipped weights."""
    pytest.importorskip("torch")
    from dadiff.export.checkpoint import load_checkpoint
    from dadiff.export.reference import TorchBackend
    from dadiff.runtime import OnnxBackend

    folder = models.resolve(models.DEFAULT_MODEL)
    torch_side = TorchBackend(load_checkpoint(folder / "checkpoint.pt"))
    onnx_side = OnnxBackend(folder, threads=1)
    rng = np.random.default_rng(11)
    z = rng.integers(0, 256, (1, 3, 127, 127)).astype(np.float32)
    size = onnx_side.input_buffer.shape[-1]  # the search crop the default ships at (223 px)
    x = rng.integers(0, 256, (1, 3, size, size)).astype(np.float32)
    ref_cls, ref_loc = torch_side.search(x, torch_side.template(z))
    cls, loc = onnx_side.search(x, onnx_side.template(z))
    assert np.abs(cls - ref_cls).max() < 1e-4
    assert np.abs(loc - ref_loc).max() / max(1.0, np.abs(ref_loc).max()) < 1e-4


@pytest.mark.parametrize("folder", _shipped(), ids=lambda p: p.name)
def test_source_sha256_names_the_file_exported_and_the_model_card_says_which(folder) -> None:
    """Issue 55: dadiff-mobile's graphs carry source_sha256 0bc3db2d..., not the hash of the checkpoint.pt
    beside them (0e74aaf0...). The graphs were exported from the training run's averaged checkpoint in
    export/resume/, and checkpoint.pt is that file set to the 223 px crop (another file, so another hash):
    the model card names the file each hash belongs to."""
    import hashlib
    from pathlib import Path

    repo = Path(__file__).resolve().parent.parent
    meta = {p.key: p.value for p in onnx.load(str(folder / "search.onnx")).metadata_props}
    folder = repo / "models" / folder.name  # checkpoint.pt stays in the checkout, out of the installed package
    card = (folder / "MODEL_CARD.md").read_text()
    assert meta["source_sha256"][:16] in card
    checkpoint = hashlib.sha256((folder / "checkpoint.pt").read_bytes()).hexdigest()
    assert checkpoint[:16] in card
    if checkpoint != meta["source_sha256"]:  # the exported file is in the repository and named in the card
        named = [p for p in (repo / "export" / "resume").glob("*.pt") if f"export/resume/{p.name}" in card]
        assert [hashlib.sha256(p.read_bytes()).hexdigest() for p in named].count(meta["source_sha256"]) == 1

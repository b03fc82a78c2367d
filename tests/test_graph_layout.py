"""`GraphLayout`: the one order of the tensors between the template graph and the search graph."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from dadiff.export.onnx_export import GraphLayout  # noqa: E402


@pytest.mark.parametrize("reads_template", [False, True])
def test_names_follow_the_documented_order(reads_template: bool) -> None:
    layout = GraphLayout(levels=2, reads_template=reads_template)
    assert layout.template_outputs() == ["zf0", "zf1", "kcls0", "kcls1", "kloc0", "kloc1"]
    features = ["zf0", "zf1"] if reads_template else []
    assert layout.search_inputs() == ["kcls0", "kcls1", "kloc0", "kloc1", *features]


@pytest.mark.parametrize("reads_template", [False, True])
def test_search_args_carry_each_template_output_to_its_named_input(reads_template: bool) -> None:
    """The reorder and the split agree with the names: each tensor arrives where its name says."""
    layout = GraphLayout(levels=3, reads_template=reads_template)
    outputs = {name: torch.full((1,), float(i)) for i, name in enumerate(layout.template_outputs())}
    args = layout.search_args(list(outputs.values()))
    assert [float(a) for a in args] == [float(outputs[name]) for name in layout.search_inputs()]
    kcls, kloc, zf = layout.split_search_args(args)
    assert [float(k) for k in kcls] == [float(outputs[f"kcls{i}"]) for i in range(3)]
    assert [float(k) for k in kloc] == [float(outputs[f"kloc{i}"]) for i in range(3)]
    if reads_template:
        assert [float(z) for z in zf] == [float(outputs[f"zf{i}"]) for i in range(3)]
    else:
        assert zf is None

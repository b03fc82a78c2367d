"""Each key of each `day` source is checked as a dadiff-train config loads: a misspelt option used to be
dropped silently, and a bad value or the held-out split surfaced only as the run started (or never), without
the file's name. Now `--show-config` refuses too, in one line naming the file, the entry and the key."""

from __future__ import annotations

import pytest

pytest.importorskip("torch")

from dadiff.export import train  # noqa: E402

SCENE_KEYS = "kind 'scenes' takes kind, split, pairs, source, companions, stretch, cutouts"
BAD_SOURCES = [
    ('{kind = "scenes", source = "library", split = "train", pairs = 2, cutout = "/nonexistent", strech = 0.5, '
     'foo = 1}',
     "'day' entry 2 (kind 'scenes') has unknown keys: cutout = '/nonexistent' (did you mean 'cutouts'?), "
     f"strech = 0.5 (did you mean 'stretch'?), foo = 1; {SCENE_KEYS}"),
    ('{kind = "scenes", source = "library", companion = 0.5}',
     f"'day' entry 2 (kind 'scenes') has unknown keys: companion = 0.5 (did you mean 'companions'?); {SCENE_KEYS}"),
    ('{kind = "scenes", far = 0.5}', "has unknown keys: far = 0.5 (a key of got10k, otb, sequences sources)"),
    ('{kind = "images", root = "f", match = "*"}',
     "'day' entry 2 (kind 'images') has unknown keys: match = '*' (a key of got10k, otb, sequences sources); "
     "kind 'images' takes kind, root"),
    ('{kind = "scenes", pairs = 0}', "'day' entry 2 (kind 'scenes'): 'pairs' is 0; expected >= 1"),
    ('{kind = "scenes", pairs = 2.5}', "'day' entry 2 (kind 'scenes'): 'pairs' is 2.5; expected an integer"),
    ('{kind = "scenes", split = "test"}',
     "'day' entry 2 (kind 'scenes'): 'split' is 'test'; expected \"train\" (the test split is held out: the "
     "evaluation scores trackers on it)"),
    ('{kind = "scenes", source = "web"}', "'source' is 'web'; expected one of skimage, library"),
    ('{kind = "scenes", source = "library", stretch = 1.5}', "'stretch' is 1.5; expected a share from 0 to 1"),
    ('{kind = "scenes", companions = true}', "'companions' is True; expected a number"),
    ('{kind = "scenes", companions = 0.5}',
     "'day' entry 2 (kind 'scenes'): 'companions' is 0.5, which applies to library scenes only; add "
     "source = \"library\" or drop 'companions'"),
    ('{kind = "scenes", cutouts = "people"}', "'cutouts' is 'people', which applies to library scenes only"),
    ('{kind = "otb", root = "f", far = -0.1}',
     "'day' entry 2 (kind 'otb'): 'far' is -0.1; expected a share from 0 to 1"),
    ('{kind = "sequences", root = "f", one_night = "yes"}', "'one_night' is 'yes'; expected true or false"),
]


@pytest.mark.parametrize(("source", "message"), BAD_SOURCES)
def test_a_bad_day_source_is_refused_as_the_config_loads(tmp_path, capsys, source: str, message: str) -> None:
    config = tmp_path / "c.toml"
    config.write_text(f'steps = 1\nday = [{{ kind = "scenes" }}, {source}]\n')
    assert train.main(["--config", str(config), "--output", str(tmp_path / "run"), "--show-config"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1, err
    assert err.startswith(f"dadiff-train: error: {config}: ") and message in err, err
    assert not (tmp_path / "run").exists()


def test_every_option_of_each_kind_still_loads(tmp_path, capsys) -> None:
    config = tmp_path / "c.toml"
    config.write_text(
        'night_pairs = "scene"\n'
        'day = [{ kind = "scenes", source = "library", split = "train", pairs = 16, companions = 0.5, stretch = 0.5, '
        'cutouts = "people" },\n'
        '       { kind = "scenes", companions = 0.0, stretch = 0 },\n'  # a share of 0 asks nothing of the library
        '       { kind = "sequences", root = "r", match = "*_day", far = 0.7, one_night = true },\n'
        '       { kind = "got10k", root = "r" }, { kind = "images", root = "f" }]\n')
    assert train.main(["--config", str(config), "--show-config"]) == 0
    assert "cutouts = \"people\"" in capsys.readouterr().out

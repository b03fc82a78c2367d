"""HIT-UAV's night stills as tracking sequences: neighbours registered, the same object's boxes linked, refusals."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.commands.eval import main as eval_main
from dadiff.runtime.datamaking.datasets import load_dataset
from dadiff.runtime.datamaking.hit_uav import CHECKOUT_DATA, ChainSettings, Registration, build_chains, read_split

SIZE = (640, 512)  # width, height of a HIT-UAV still


def _ground(seed: int = 0) -> np.ndarray:
    """A textured 'world' (roads, roofs: smoothed noise) that the stills are cut from, so ORB finds corners."""
    rng = np.random.default_rng(seed)
    noise = cv2.resize(rng.integers(0, 255, (120, 150), dtype=np.uint8), (1200, 960), interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(noise, (3, 3), 0)


def _still(world: np.ndarray, offset: tuple[int, int], objects: list[tuple[float, float, float, float]]) -> np.ndarray:
    image = world.copy()
    for x, y, w, h in objects:  # warm bodies: white-hot blobs
        cv2.rectangle(image, (int(x), int(y)), (int(x + w) - 1, int(y + h) - 1), 250, -1)
    ox, oy = offset
    return image[oy:oy + SIZE[1], ox:ox + SIZE[0]]


def _fake_hit_uav(root: Path, stills: list[dict], split: str = "test") -> Path:
    """A folder in HIT-UAV's layout: images/<name>.jpg and annotations/<split>.json (boxes under 'annotation').

    Each still: name, offset (where the camera looks in the world) and objects [(class, world box)]."""
    (root / "images").mkdir(parents=True)
    (root / "annotations").mkdir()
    world = _ground()
    images, annotations = [], []
    for k, still in enumerate(stills):
        boxes = [box for _, box in still["objects"]]
        cv2.imwrite(str(root / "images" / still["name"]), _still(world, still["offset"], boxes))
        images.append({"filename": still["name"], "height": SIZE[1], "width": SIZE[0], "id": 100 + k})
        for cls, (x, y, w, h) in still["objects"]:
            box = [x - still["offset"][0], y - still["offset"][1], w, h]
            annotations.append({"bbox": box, "category_id": cls, "image_id": 100 + k, "id": len(annotations) + 1,
                                "area": w * h})
    doc = {"info": {}, "images": images, "annotation": annotations, "categories": []}
    (root / "annotations" / f"{split}.json").write_text(json.dumps(doc))
    return root


CAR = (1, (500.0, 400.0, 30.0, 16.0))
PERSON = (0, (700.0, 300.0, 10.0, 12.0))


def _flight(prefix: str = "1_60_30_0") -> list[dict]:
    """Three stills of one flight, the camera moving 37 then 55 px; a car and a person in all three."""
    return [{"name": f"{prefix}_{index:05d}.jpg", "offset": offset, "objects": [CAR, PERSON]}
            for index, offset in ((10, (300, 200)), (12, (337, 210)), (15, (392, 190)))]


def test_neighbouring_stills_link_each_object_into_one_sequence_with_its_true_boxes(tmp_path):
    root = _fake_hit_uav(tmp_path / "hit", _flight())
    out = tmp_path / "out"
    assert eval_main(["hit-uav", "--data", str(root), "--output", str(out)]) == 0
    dataset = load_dataset(out)
    assert sorted(s.name for s in dataset.sequences) == ["hit0001_car", "hit0002_person"]
    car = next(s for s in dataset.sequences if s.name.endswith("car"))
    assert len(car) == 3 and car.attributes == ("car",)
    expected = [[500 - ox, 400 - oy, 30, 16] for ox, oy in ((300, 200), (337, 210), (392, 190))]
    np.testing.assert_allclose(car.boxes, expected)
    # the frames are the stills' own bytes, not re-encoded copies
    assert car.frames[1].read_bytes() == (root / "images" / "1_60_30_0_00012.jpg").read_bytes()
    info = json.loads((out / "benchmark.json").read_text())
    assert info["split"] == "test" and "CC BY 4.0" in info["licence"] and "HIT-UAV" in info["attribution"]
    record = next(r for r in info["sequences"] if r["name"] == "hit0001_car")
    assert record["images"] == ["1_60_30_0_00010.jpg", "1_60_30_0_00012.jpg", "1_60_30_0_00015.jpg"]
    shift = np.array(info["pairs"][0]["transform"])[:, 2]
    np.testing.assert_allclose(shift, [-37, -10], atol=1.0)  # registration found the camera's move


def test_max_move_keeps_only_links_within_a_trackers_reach(tmp_path):
    """The camera moves 38 then 58 px: 1.7 and 2.7 sides of the car (22 px), 3.5 and 5.3 of the person (11 px)."""
    root = _fake_hit_uav(tmp_path / "hit", _flight())
    out = tmp_path / "out"
    assert eval_main(["hit-uav", "--data", str(root), "--output", str(out), "--max-move", "2"]) == 0
    dataset = load_dataset(out)
    assert [(s.name, len(s)) for s in dataset.sequences] == [("hit0001_car", 2)]
    assert json.loads((out / "benchmark.json").read_text())["settings"]["max_move"] == 2


def test_a_look_alike_beside_the_target_is_refused_not_guessed(tmp_path):
    twin = (0, (PERSON[1][0] + 14, PERSON[1][1], 10.0, 12.0))  # another person 14 px to the right
    stills = _flight()
    for still in stills:
        still["objects"] = [CAR, PERSON, twin]
    root = _fake_hit_uav(tmp_path / "hit", stills)
    chains, _ = build_chains(read_split(root, "test"), Registration(root / "images", ChainSettings()))
    assert [c.cls for c in chains] == [1]  # the car only: which person is which cannot be told


def test_stills_of_other_flights_or_far_apart_are_not_linked(tmp_path):
    stills = _flight()
    stills[1]["name"] = "1_70_30_0_00012.jpg"  # another flight (altitude) between them
    stills[2]["name"] = "1_60_30_0_00090.jpg"  # 80 video frames after the first: beyond --max-gap
    stills.append({"name": "0_60_30_0_00011.jpg", "offset": (300, 200), "objects": [CAR]})  # a day image
    root = _fake_hit_uav(tmp_path / "hit", stills)
    split = read_split(root, "test")
    assert [s.name for s in split] == ["1_60_30_0_00010.jpg", "1_60_30_0_00090.jpg", "1_70_30_0_00012.jpg"]
    chains, _ = build_chains(split, Registration(root / "images", ChainSettings()))
    assert chains == []
    status = eval_main(["hit-uav", "--data", str(root), "--output", str(tmp_path / "out")])
    assert status == 2 and not (tmp_path / "out").exists()


def test_a_camera_jump_without_common_ground_is_not_linked(tmp_path):
    stills = _flight()
    stills[1]["offset"] = (0, 0)  # the next still looks elsewhere: its boxes must not be paired by chance
    stills[1]["objects"] = [(1, (100.0, 100.0, 30.0, 16.0))]
    stills = stills[:2]
    stills[1]["objects"] = []
    root = _fake_hit_uav(tmp_path / "hit", stills)
    blank = np.full((SIZE[1], SIZE[0]), 128, np.uint8)  # a featureless still: nothing to register on
    cv2.imwrite(str(root / "images" / stills[1]["name"]), blank)
    chains, pairs = build_chains(read_split(root, "test"), Registration(root / "images", ChainSettings()))
    assert chains == [] and pairs[0]["registered"] is False


@pytest.mark.parametrize(("doc", "expected"), [
    ("{", "not JSON"),
    ('{"images": []}', "no 'annotation' list"),
    ('{"images": [], "annotation": [{"bbox": [1, 2]}]}', "annotation 0"),
    ('{"images": [{"filename": "1_60_30_0_00001.jpg", "id": "x"}], "annotation": []}', "image 0"),
])
def test_bad_annotations_get_one_line_and_exit_2(tmp_path, capsys, doc, expected):
    root = _fake_hit_uav(tmp_path / "hit", _flight())
    (root / "annotations" / "test.json").write_text(doc)
    assert eval_main(["hit-uav", "--data", str(root), "--output", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "test.json" in err[0] and expected in err[0]


@pytest.mark.skipif(not (CHECKOUT_DATA / "annotations" / "val.json").is_file(), reason="no ../shared HIT-UAV data")
def test_real_hit_uav_neighbours_link_into_sequences_of_one_class():
    stills = read_split(CHECKOUT_DATA, "val")
    assert len(stills) == 195 and all(s.name.startswith("1_") for s in stills)
    first = stills[:12]  # a few flights' worth keeps the test to seconds
    chains, pairs = build_chains(first, Registration(CHECKOUT_DATA / "images", ChainSettings()))
    assert any(p["registered"] for p in pairs) and chains
    for chain in chains:
        assert len({first[p].flight for p in chain.stills}) == 1
        assert all(first[p].classes[r] == chain.cls for p, r in zip(chain.stills, chain.boxes, strict=True))


def test_a_damaged_still_is_one_line_naming_it_and_exit_2(tmp_path, capsys):
    root = _fake_hit_uav(tmp_path / "hit", _flight())
    (root / "images" / "1_60_30_0_00012.jpg").write_bytes(b"not a jpeg")
    assert eval_main(["hit-uav", "--data", str(root), "--output", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"dadiff-eval: error: {root / 'images' / '1_60_30_0_00012.jpg'}: cannot read image"]

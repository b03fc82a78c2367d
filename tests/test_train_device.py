"""export/device_train.sh, run here on the CPU: its `train` mode shows dadiff-train's own lines (an error, where
the run stopped) while dropping the per-step progress, and exits with dadiff-train's exit code (a failed GPU
run used to show nothing and exit 0); `merge` brings the device's last.pt and log.csv rows into the run."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "export" / "device_train.sh"
pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")


def _script(*args: str, root: Path = REPO, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"  # python3: this interpreter
    return subprocess.run(["bash", str(root / "export" / "device_train.sh"), *args], capture_output=True, text=True,
                          env={**os.environ, "PATH": path, **(env or {})}, timeout=300)


def _write_log(path: Path, fields: list[str], steps: range) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(fields)
        writer.writerows([[str(step)] + ["0.5"] * (len(fields) - 1) for step in steps])


def _read_log(path: Path) -> tuple[list[str], list[int]]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], [int(row[0]) for row in rows[1:]]


def test_merge_brings_last_pt_back_and_appends_the_devices_log_rows(tmp_path):
    device, run = tmp_path / "files", tmp_path / "run"
    device.mkdir()
    run.mkdir()
    (device / "last.pt").write_bytes(b"device state")
    old = ["step", "lr", "total"]  # a log begun before a column was added keeps its own header
    _write_log(run / "log.csv", old, range(1, 6))  # steps 4-5 ran here after the state the device resumed from
    _write_log(device / "log.csv", [*old, "night_distill"], range(4, 7))
    for _ in range(2):  # merging twice changes nothing
        done = _script("merge", str(device), str(run))
        assert done.returncode == 0, done.stderr
        assert (run / "last.pt").read_bytes() == b"device state" and not (run / "final.pt").exists()
        assert _read_log(run / "log.csv") == (old, [1, 2, 3, 4, 5, 6])
    assert "3 rows of this run, then 3 of the device's" in done.stdout
    _write_log(device / "log.csv", old, range(0))  # the device ran no step: the run's log stays
    assert _script("merge", str(device), str(run)).returncode == 0
    assert _read_log(run / "log.csv") == (old, [1, 2, 3, 4, 5, 6])


@pytest.fixture(scope="module")
def checkout(tmp_path_factory) -> Path:
    """A checkout of links to this one's code, with no .device/ (nothing to install, no state to resume)."""
    root = tmp_path_factory.mktemp("checkout")
    for part in ("export", "runtime", "drone", "models"):
        (root / part).symlink_to(REPO / part)
    return root


def _config(tmp_path: Path, body: str) -> Path:
    pytest.importorskip("torch")
    cv2 = pytest.importorskip("cv2")
    data = pytest.importorskip("skimage.data")
    images = tmp_path / "images"
    images.mkdir(exist_ok=True)
    cv2.imwrite(str(images / "chelsea.jpg"), data.chelsea()[:, :, ::-1])
    config = tmp_path / "c.toml"
    config.write_text(f'stage = "baseline"\nsteps = 1\nday = [{{ kind = "images", root = "{images}" }}]\n{body}\n')
    return config


def _train(checkout: Path, config: Path, out: Path) -> subprocess.CompletedProcess:
    return _script("train", str(config), "1", root=checkout,
                   env={"OUT": str(out), "DEVICE_BATCH": "2", "DEVICE_WORKERS": "0"})


def test_train_shows_a_failed_runs_error_and_exits_with_its_code(tmp_path, checkout):
    done = _train(checkout, _config(tmp_path, f'init = "{tmp_path / "gone.pt"}"'), tmp_path / "out")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "dadiff-train: error: " in done.stdout and f"'init' is '{tmp_path / 'gone.pt'}': no such file" in done.stdout


def test_train_refuses_a_bad_config_naming_the_given_file(tmp_path, checkout):
    config = _config(tmp_path, "stepz = 3")
    done = _train(checkout, config, tmp_path / "out")
    assert done.returncode == 2
    assert f"dadiff-train: error: {config}: unknown config keys: stepz" in done.stderr


def test_train_keeps_where_the_run_ended_and_drops_the_progress_lines(tmp_path, checkout):
    done = _train(checkout, _config(tmp_path, ""), tmp_path / "out")  # one step on the CPU
    assert done.returncode == 0, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    assert any(line.startswith("dadiff-train: step 1/1; done") for line in lines), done.stdout
    assert not any(line.startswith("baseline: ") for line in lines), done.stdout
    assert {"last.pt", "log.csv", "final.pt"} <= {p.name for p in (tmp_path / "out").iterdir()}

"""sd_notify by hand, the unit file, logging to a rotating file, the link's connection-string handling."""

from __future__ import annotations

import configparser
import logging
import os
import socket
from pathlib import Path

import pytest

from dadiff.drone.link import split_device
from dadiff.drone.logs import Throttle, log_handlers, service_logging
from dadiff.drone.systemd import Notifier

UNIT = Path(__file__).resolve().parents[1] / "drone" / "dadiff-tracker.service"


def test_notify_datagrams(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        sock.settimeout(2)
        n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "4000000", "WATCHDOG_PID": str(os.getpid())})
        assert n.enabled and n.watchdog_interval == 2.0
        assert n.ready("up") and n.watchdog() and n.status("tracking") and n.stopping()
        got = [sock.recv(256).decode() for _ in range(4)]
    assert got == ["READY=1\nSTATUS=up", "WATCHDOG=1", "STATUS=tracking", "STOPPING=1"]


def test_notify_abstract_socket_and_absence() -> None:
    name = f"dadiff-test-{os.getpid()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)
        sock.settimeout(2)
        assert Notifier({"NOTIFY_SOCKET": "@" + name}).ready()
        assert sock.recv(64) == b"READY=1"
    off = Notifier({})
    assert not off.enabled and not off.ready() and off.watchdog_interval is None
    assert Notifier({"WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"}).watchdog_interval is None  # not ours
    assert not Notifier({"NOTIFY_SOCKET": "/nonexistent/socket"}).watchdog()  # never raises


def test_unit_file() -> None:
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment]
    unit.read_string(UNIT.read_text())
    service = unit["Service"]
    assert service["Type"] == "notify" and service["Restart"] == "on-failure"
    assert int(service["WatchdogSec"]) > 0 and service["NotifyAccess"] == "main"
    assert service["ExecStart"].split()[1:] == ["--config", "/etc/dadiff/tracker.toml"]
    assert unit["Install"]["WantedBy"] == "multi-user.target"
    # the graph cache where systemd makes a folder for the user (it has no home; ProtectHome hides one)
    assert service["CacheDirectory"] == "dadiff"
    assert "Environment=DADIFF_CACHE_DIR=/var/cache/dadiff/ort" in UNIT.read_text()


def test_rotating_log_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = tmp_path / "tracker.log"
    logger = logging.getLogger("dadiff")
    before = list(logger.handlers), logger.propagate
    with service_logging("INFO", log_handlers(path, max_bytes=10_000, backups=2)):
        for k in range(400):
            logging.getLogger("dadiff.drone.test").info("line %d %s", k, "x" * 60)
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["tracker.log", "tracker.log.1", "tracker.log.2"]
    assert "line 399" in path.read_text()
    assert "line 399" in capsys.readouterr().out  # stdout too (journald under systemd)
    assert (list(logger.handlers), logger.propagate) == before  # restored
    with pytest.raises(OSError):
        log_handlers(tmp_path / "no" / "such" / "dir.log")


def test_throttle(caplog: pytest.LogCaptureFixture) -> None:
    throttle = Throttle(logging.getLogger("dadiff.test.throttle"), every=3600)
    with caplog.at_level(logging.WARNING, logger="dadiff.test.throttle"):
        for _ in range(50):
            throttle.log(logging.WARNING, "k", "bad packet")
        throttle.log(logging.WARNING, "other", "another")
    assert [r.getMessage() for r in caplog.records] == ["bad packet", "another"]


def test_throttle_of_a_condition_counts_no_loop_ticks(caplog: pytest.LogCaptureFixture, monkeypatch) -> None:
    now = [0.0]
    monkeypatch.setattr("dadiff.drone.logs.time.monotonic", lambda: now[0])
    throttle = Throttle(logging.getLogger("dadiff.test.quiet"), every=5)
    with caplog.at_level(logging.WARNING, logger="dadiff.test.quiet"):
        for second in range(11):  # one check a second: reported at 0, 5 and 10 s
            now[0] = float(second)
            throttle.log(logging.WARNING, "quiet", "nothing received", counted=False)
            throttle.log(logging.WARNING, "bad", "bad packet")
    quiet = [r.getMessage() for r in caplog.records if "nothing" in r.getMessage()]
    assert quiet == ["nothing received"] * 3  # was: "(4 more since the last report)", loop ticks, not events
    assert "(4 more since the last report)" in [r.getMessage() for r in caplog.records][-1]


def test_split_device() -> None:
    assert split_device("/dev/ttyAMA0,921600") == ("/dev/ttyAMA0", 921600)
    assert split_device("udpin:0.0.0.0:14550") == ("udpin:0.0.0.0:14550", None)
    assert split_device("tcp:10.0.0.1:5760") == ("tcp:10.0.0.1:5760", None)

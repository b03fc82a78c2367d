"""`dadiff-run --mavlink CONN`: the tracker as a MAVLink camera component (and optional follow controller)
on a companion computer.

dadiff.runtime.commands.run calls `add_mavlink_arguments(parser)` while building its parser and
`run_mavlink(args)` when --mavlink is given; `dadiff.drone.config.parse_args` adds `--config FILE.toml`.
This module imports nothing heavy at import time: the runtime's parser can load it cheaply.

Exit codes: 0 stopped (SIGTERM, end of a video file, --max-frames), 1 a loop died (systemd restarts the
service), 2 bad input (one `dadiff-run: error:` line on stderr), 130 Ctrl-C.
"""

from __future__ import annotations

import argparse
import errno
import ipaddress
import math
import re
import signal
import socket
import sys
import threading
from pathlib import Path
from typing import Any

from dadiff.runtime.argtypes import float_in, int_in

PROG = "dadiff-run"


ALLOWED_DEFAULT = frozenset({255, 245})  # QGroundControl, MAVSDK (camera.DEFAULT_ALLOWED; no pymavlink here)


def _sysids(text: str) -> frozenset[int] | None:
    """'255,245' → {255, 245}; 'any' → None (every sender)."""
    if text.strip().lower() == "any":
        return None
    try:
        values = frozenset(int(p) for p in text.replace(" ", "").split(",") if p)
    except ValueError:
        values = frozenset({-1})
    if not values or not all(1 <= v <= 255 for v in values):
        raise argparse.ArgumentTypeError(f"expected system ids 1-255 separated by commas, or 'any', got {text!r}")
    return values


def _stream_url(text: str) -> str:
    url = text.strip()
    if not url or len(url.encode()) > 160:
        raise argparse.ArgumentTypeError(f"expected a stream URL of 1 to 160 bytes, got {text!r}")
    return url


NETWORK_SCHEMES = ("udpin", "udpout", "udpbcast", "udp", "tcp", "tcpin", "mcast")
SOCKET_SCHEMES = ("uds", "unix")
CONN_FORMS = "udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT or a serial port /dev/ttyX[,BAUD]"


def _network_ok(rest: str) -> bool:
    host, sep, port = rest.rpartition(":")
    return bool(sep and host.strip() and port.isdigit() and 1 <= int(port) <= 65535)


def _serial_ok(text: str) -> bool:
    device, sep, baud = text.partition(",")
    if sep and not (baud.isdigit() and int(baud) > 0):
        return False
    return device.startswith("/dev/") and len(device) > 5 or bool(re.fullmatch(r"COM\d+", device, re.IGNORECASE))


def _bad_ipv4(host: str) -> bool:
    """Dotted digits that are no IPv4 address (999.1.1.1): the link would retry it forever."""
    if not re.fullmatch(r"[\d.]+", host):
        return False
    try:
        ipaddress.IPv4Address(host)
    except ValueError:
        return True
    return False


def mavlink_conn(text: str) -> str:
    """argparse type: a connection string pymavlink opens as a link (it opens anything else as a log file,
    so a spec without a known scheme, `foo:bar`, is refused here rather than run without a link)."""
    spec = text.strip()
    scheme, sep, rest = spec.partition(":")
    host = rest.rpartition(":")[0]
    if sep and scheme in NETWORK_SCHEMES and (":" in host or "[" in host):  # pymavlink splits on every ':'
        raise argparse.ArgumentTypeError(f"pymavlink's {scheme} links take an IPv4 address or a host name, "
                                         f"not an IPv6 address, got {text!r}")
    if sep and scheme in NETWORK_SCHEMES and _bad_ipv4(host.strip()):
        raise argparse.ArgumentTypeError(f"{host.strip()!r} is not an IPv4 address, in {text!r}")
    ok = (sep and scheme in NETWORK_SCHEMES and _network_ok(rest)) or (
        sep and scheme in SOCKET_SCHEMES and rest.strip()) or _serial_ok(spec)
    if not ok:
        raise argparse.ArgumentTypeError(f"expected {CONN_FORMS}, got {text!r}")
    return spec


def check_endpoint(url: str) -> None:
    """ValueError (one line) before the link first opens: a host that does not resolve (a `udpout:` to one
    would log "open" and send nowhere), or a `udp:`/`udpin:`/`tcpin:` address this machine cannot listen on, its
    port held by another program included (a second service on one udpin port would silently take the ground
    station's traffic while the first heartbeats on). Serial ports and later reopens are left to the link's retries."""
    scheme, sep, rest = url.partition(":")
    if not sep or scheme not in NETWORK_SCHEMES:
        return
    host, _, port = rest.rpartition(":")
    kind = socket.SOCK_STREAM if scheme.startswith("tcp") else socket.SOCK_DGRAM
    try:
        address = socket.getaddrinfo(host, int(port), socket.AF_INET, kind)[0][4]
    except (socket.gaierror, UnicodeError) as exc:
        raise ValueError(f"--mavlink {url}: cannot resolve host '{host}' ({getattr(exc, 'strerror', exc)})") from None
    if scheme not in ("udp", "udpin", "tcpin"):  # pymavlink's plain udp: listens, as udpin: does
        return
    with socket.socket(socket.AF_INET, kind) as probe:
        if kind == socket.SOCK_STREAM:  # as pymavlink binds: our last run's TIME_WAIT is no conflict, a listener is
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            why = ("in use by another program (another dadiff service?)" if exc.errno == errno.EADDRINUSE
                   else exc.strerror or str(exc))
            raise ValueError(f"--mavlink {url}: cannot listen on {host}:{port}: {why}") from None


def add_mavlink_arguments(parser: argparse.ArgumentParser) -> None:
    """The MAVLink, follow, service and logging options (and --config); adding them twice is a no-op."""
    if "--mavlink" in parser._option_string_actions:
        return
    parser.add_argument(
        "--config",
        type=Path,
        metavar="FILE.toml",
        help='read options from a TOML file: each long option is a key (video = "/dev/video0", '
        "follow = true, init = [612, 300, 24, 18]); the command line overrides it",
    )
    g = parser.add_argument_group("MAVLink camera component (companion computer)")
    g.add_argument(
        "--mavlink",
        type=mavlink_conn,
        metavar="CONN",
        help="run as a MAVLink camera on this pymavlink connection: udpin:0.0.0.0:14560, "
        "udpout:HOST:PORT, tcp:HOST:PORT, or a serial port /dev/ttyAMA0,921600. Without --init, "
        "tracking starts when a ground station sends a track command",
    )
    g.add_argument("--dialect", choices=("ardupilotmega", "common"), default="ardupilotmega",
                   help="MAVLink dialect (default: ardupilotmega)")
    g.add_argument(
        "--sysid",
        type=int_in(1, 254),
        help="our system id (the vehicle's); default: speak at once as 1 and adopt the autopilot's id from its "
        "heartbeat",
    )
    g.add_argument("--component", type=int_in(100, 105), default=100, help="camera component id (default 100)")
    g.add_argument(
        "--allow-sysid",
        type=_sysids,
        default=ALLOWED_DEFAULT,
        metavar="IDS",
        help="system ids whose commands are accepted besides the vehicle's own: a list such as 255,245 "
        "(the default: QGroundControl and MAVSDK) replaces the default, 'any' accepts everyone; with "
        "--signing-key every correctly signed sender is accepted too. Others get COMMAND_ACK DENIED",
    )
    g.add_argument(
        "--signing-key",
        type=Path,
        metavar="FILE",
        help="MAVLink 2 signing key: 32 raw bytes, 64 hex digits, or a passphrase (SHA-256); "
        "unsigned packets are then rejected",
    )
    g.add_argument(
        "--tracking-rate",
        type=float_in(0, 50),
        default=10.0,
        metavar="HZ",
        help="CAMERA_TRACKING_IMAGE_STATUS rate while tracking (default 10; 0: only when asked); "
        "ground stations change it with MAV_CMD_SET_MESSAGE_INTERVAL",
    )
    g.add_argument(
        "--stream-url",
        type=_stream_url,
        metavar="URL",
        help="advertise this video stream to ground stations (VIDEO_STREAM_INFORMATION, e.g. "
        "rtsp://192.168.1.10:8554/cam) at the resolution the tracker sees",
    )
    g.add_argument(
        "--realtime",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="with --mavlink, play a video file at its own frame rate, as a camera would deliver it "
        "(default; --no-realtime: as fast as it decodes), to rehearse with a recorded flight",
    )
    g.add_argument("--loop", action="store_true", help="with --mavlink, play a video file again at its end")
    g.add_argument(
        "--link-timeout",
        type=float_in(0.5, 600),
        default=5.0,
        metavar="S",
        help="reopen a serial or TCP link after this long without a message (default 5; UDP links stay "
        "up and keep sending)",
    )
    f = parser.add_argument_group("follow controller (off by default)")
    f.add_argument(
        "--follow",
        nargs="?",
        const="vehicle",
        choices=("vehicle", "gimbal"),
        metavar="vehicle|gimbal",
        help="vehicle (the default with no value): send body-frame velocity setpoints that keep the target "
        "centred and at its starting size, only while armed in ArduCopter GUIDED or PX4 OFFBOARD; gimbal: "
        "point the gimbal at the target through the MAVLink gimbal manager (takes primary control)",
    )
    f.add_argument("--follow-rate", type=float_in(10, 20), default=15.0, metavar="HZ",
                   help="setpoint rate, 10-20 (default 15)")
    f.add_argument("--max-speed", type=float_in(0, 20, open_low=True), default=3.0, metavar="M/S",
                   help="horizontal speed limit (default 3)")
    f.add_argument("--max-climb", type=float_in(0, 10, open_low=True), default=1.0, metavar="M/S",
                   help="vertical speed limit with --follow-altitude (default 1)")
    f.add_argument("--max-yaw-rate", type=float_in(0, 360, open_low=True), default=45.0, metavar="DEG/S",
                   help="yaw rate limit (default 45)")
    f.add_argument("--max-accel", type=float_in(0, 20, open_low=True), default=2.0, metavar="M/S2",
                   help="acceleration limit (default 2)")
    f.add_argument(
        "--follow-altitude", action="store_true", help="also climb or descend to centre the target (default: hold)"
    )
    f.add_argument("--yaw-gain", type=float_in(0, 10), default=1.0,
                   help="rad/s per unit horizontal error (default 1)")
    f.add_argument("--lateral-gain", type=float_in(0, 10), default=0.0,
                   help="m/s per unit horizontal error (default 0)")
    f.add_argument("--forward-gain", type=float_in(0, 20), default=2.0,
                   help="m/s per unit log-size error (default 2)")
    f.add_argument("--vertical-gain", type=float_in(0, 10), default=1.0,
                   help="m/s per unit vertical error (default 1)")
    f.add_argument(
        "--gimbal-rate", type=float_in(10, 50), default=20.0, metavar="HZ", help="gimbal setpoint rate (default 20)"
    )
    f.add_argument(
        "--gimbal-gain", type=float_in(0, 10, open_low=True), default=1.0,
        help="gimbal rad/s per unit offset (default 1)",
    )
    f.add_argument(
        "--max-gimbal-rate", type=float_in(0, 360, open_low=True), default=60.0, metavar="DEG/S",
        help="gimbal pitch and yaw rate limit (default 60)",
    )  # fmt: skip
    f.add_argument(
        "--gimbal-device", type=int_in(0, 255), default=0, metavar="ID",
        help="gimbal device id at the gimbal manager (default 0: all)",
    )  # fmt: skip
    s = parser.add_argument_group("service logging")
    s.add_argument("--log-file", type=Path, metavar="FILE", help="also log to this rotating file")
    s.add_argument("--log-max-bytes", type=int_in(10_000, 10**10), default=10_000_000, metavar="N",
                   help="rotate the log file at this size (default 10000000)")
    s.add_argument("--log-backups", type=int_in(0, 100), default=5, metavar="N",
                   help="rotated log files kept (default 5)")
    s.add_argument("--log-level", choices=("DEBUG", "INFO", "WARNING", "ERROR"), default="INFO",
                   help="(default: INFO)")


SERVICE_GROUPS = ("MAVLink camera component (companion computer)", "follow controller (off by default)",
                  "service logging")


def service_options_given(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[str]:
    """The service's options set away from `parser`'s defaults (give a fresh parser: --config sets defaults), but
    --mavlink: without --mavlink they apply to nothing (`--follow gimbal` would run a plain track and exit 0)."""
    given = []
    for group in parser._action_groups:
        if group.title in SERVICE_GROUPS:
            given += [action.option_strings[0] for action in group._group_actions
                      if action.dest != "mavlink" and getattr(args, action.dest, None) != action.default]
    return given


def _error(message: object) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return 2


def _path_problem(spec: str) -> str | None:
    """Why a video given as a path cannot be one (missing, a FIFO); cameras and streams may appear later."""
    from dadiff.runtime.sources import SourceError, source_path

    if spec.isdigit() or spec.startswith("/dev/") or "://" in spec:
        return None
    try:
        source_path(spec)
    except SourceError as exc:
        return str(exc)
    return None


def _settings(args: argparse.Namespace, key: bytes | None) -> Any:
    from dadiff.runtime.crop import protocol_box

    from .camera import CameraSettings
    from .follow import FollowConfig, Gains, Limits
    from .gimbal import GimbalConfig
    from .link import LinkSettings
    from .service import ServiceSettings

    follow = gimbal = None
    if args.follow == "gimbal":
        gimbal = GimbalConfig(
            rate_hz=args.gimbal_rate,
            gain=args.gimbal_gain,
            max_rate=math.radians(args.max_gimbal_rate),
            gimbal_device_id=args.gimbal_device,
        )
    elif args.follow:
        follow = FollowConfig(
            gains=Gains(args.yaw_gain, args.lateral_gain, args.vertical_gain, args.forward_gain),
            limits=Limits(
                args.max_speed, args.max_climb, math.radians(args.max_yaw_rate), args.max_accel, math.radians(90)
            ),
            altitude=args.follow_altitude,
            rate_hz=args.follow_rate,
        )
    init = getattr(args, "init", None)
    if init is not None:
        init = protocol_box(init)  # the convention of dadiff-run --init (the released toolkit's)
    return ServiceSettings(
        link=LinkSettings(
            args.mavlink, args.dialect, args.component, args.sysid, key, silence_timeout=args.link_timeout
        ),
        camera=CameraSettings(
            args.component,
            args.tracking_rate,
            allowed_sysids=args.allow_sysid,
            trust_signed=key is not None,
            stream_url=args.stream_url,
        ),
        follow=follow,
        gimbal=gimbal,
        init_box=init,
        max_frames=getattr(args, "max_frames", None),
        realtime=args.realtime,
        loop=args.loop,
    )


def run_mavlink(args: argparse.Namespace) -> int:
    """Run the service until SIGTERM / Ctrl-C, the end of a video file, or --max-frames; the exit code."""
    from .logs import log_handlers, service_logging

    video = getattr(args, "video", None)
    if not video:
        return _error("--mavlink needs --video (the camera: 0, /dev/video0, rtsp://...)")
    if (problem := _path_problem(video)) is not None:
        return _error(problem)
    from dadiff.runtime.errors import os_error_line
    from dadiff.runtime.outputs import OutputError, check_distinct

    try:  # before the log file is opened: it appends to (or rotates away) whatever it names
        check_distinct(video, {"--output": getattr(args, "output", None),
                               "--save-video": getattr(args, "save_video", None), "--log-file": args.log_file})
    except OutputError as exc:
        return _error(exc)
    except OSError as exc:  # an input the user may not read (a chmod 700 image folder)
        return _error(os_error_line(exc))
    try:
        check_endpoint(args.mavlink)
    except ValueError as exc:
        return _error(exc)
    try:
        handlers = log_handlers(args.log_file, args.log_max_bytes, args.log_backups)
    except OSError as exc:
        return _error(f"{args.log_file}: cannot write the log ({exc.strerror or exc})")
    with service_logging(args.log_level, handlers):
        return _run(args, video)


def _run(args: argparse.Namespace, video: str) -> int:
    from dadiff.runtime.cpu import warn_int8
    from dadiff.runtime.errors import DadiffError
    from dadiff.runtime.outputs import Sink, TrackLog, VideoSink
    from dadiff.runtime.sources import open_source
    from dadiff.runtime.tracker import Tracker

    from .service import Service
    from .signing import load_key
    from .systemd import Notifier

    sinks: list[Sink] = []
    try:
        output, save_video = getattr(args, "output", None), getattr(args, "save_video", None)  # checked before
        key = load_key(args.signing_key) if args.signing_key is not None else None
        tracker = Tracker.load(
            getattr(args, "model", None),
            provider=getattr(args, "provider", None),
            threads=getattr(args, "threads", None),
            preset=getattr(args, "preset", None),
            overrides=getattr(args, "hp", None) or None,
        )
        warn_int8(PROG, tracker)
        if output is not None:
            sinks.append(TrackLog(output))
        if save_video is not None:
            sinks.append(VideoSink(save_video, None))
    except DadiffError as exc:
        for sink in sinks:
            sink.close()
        return _error(exc)
    service = Service(_settings(args, key), tracker, lambda: open_source(video), sinks, Notifier())
    rc = _run_with_signals(service)
    if service.tracking.startup_error is not None:  # --init that the first frame refuses: exit 2, as without --mavlink
        return _error(service.tracking.startup_error)
    return rc


def _run_with_signals(service: Any) -> int:
    """SIGTERM stops cleanly (exit 0), Ctrl-C and SIGHUP (a dropped SSH session) too (exit 130); handlers only
    in the main thread; a signal the process was started ignoring (nohup's SIGHUP) stays ignored."""
    if threading.current_thread() is not threading.main_thread():
        return service.run()
    caught: list[int] = []

    def stop(signum: int, frame: object) -> None:
        first = not caught
        caught.append(signum)
        if first:  # a second signal inside the first one's Event.set() would deadlock on its lock
            service.stop()

    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
                if signal.getsignal(sig) is not signal.SIG_IGN}
    try:
        rc = service.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 130 if {signal.SIGINT, signal.SIGHUP} & set(caught) and rc == 0 else rc

"""The MAVLink connection: open from a pymavlink connection string, receive, send, sign, and reopen by
itself after loss. Owned by one thread (the MAVLink loop); nothing here blocks for long.

Loss is an exception from the socket or serial port, end of file on TCP, or (serial and TCP only)
`silence_timeout` seconds without a single message; the link is then closed and reopened with a growing
delay (`retry_min` to `retry_max`). A UDP link is never torn down for silence: a `udpout:` peer that has
not spoken yet (mavlink-router, a ground station listening) waits to hear from us first, and reopening would
only cost heartbeats; the silence is logged (throttled) instead.

System id: `sysid` when given; otherwise we speak at once as system DEFAULT_SYSID (1, what autopilots use
out of the box) and adopt the autopilot's id from its first HEARTBEAT (component 1, autopilot not
MAV_AUTOPILOT_INVALID), logged; after that, heartbeats of another system are ignored. Never 255 (a GCS).
"""

from __future__ import annotations

import logging
import socket
import struct
from dataclasses import dataclass
from typing import Any

from .logs import Throttle
from .mav import mavlink, mavutil
from .signing import SignatureCheck, UnsignedPolicy

log = logging.getLogger(__name__)

SIGNING_LINK_ID = 1
DEFAULT_SYSID = 1  # our system id until the autopilot's heartbeat says otherwise


@dataclass(frozen=True)
class LinkSettings:
    url: str
    dialect: str = "ardupilotmega"
    component: int = mavlink.MAV_COMP_ID_CAMERA
    sysid: int | None = None
    signing_key: bytes | None = None
    silence_timeout: float = 5.0
    retry_min: float = 0.5
    retry_max: float = 5.0


def split_device(url: str) -> tuple[str, int | None]:
    """'/dev/ttyAMA0,921600' → ('/dev/ttyAMA0', 921600); other strings pass unchanged."""
    device, sep, baud = url.rpartition(",")
    if sep and device and baud.strip().isdigit():
        return device, int(baud)
    return url, None


def is_autopilot_heartbeat(msg: Any) -> bool:
    return (
        getattr(msg, "autopilot", mavlink.MAV_AUTOPILOT_INVALID) != mavlink.MAV_AUTOPILOT_INVALID
        and msg.get_srcComponent() == mavlink.MAV_COMP_ID_AUTOPILOT1
        and msg.get_srcSystem() not in (0, 255)
    )


def _drop_partial_frame(mav: Any) -> None:
    """Forget bytes of a frame that its datagram did not complete (MAVLink frames never span datagrams)."""
    mav.buf, mav.buf_index = bytearray(), 0
    mav.expected_length = mavlink.HEADER_LEN_V1 + 2


MAX_FRAME = 280  # MAVLink 2: 10 header + 255 payload + 2 CRC + 13 signature bytes
MAX_RESYNC = 64  # frame starts tried in one damaged datagram before the rest is dropped (bounds the work)
MAGIC = (mavlink.PROTOCOL_MARKER_V1, mavlink.PROTOCOL_MARKER_V2)


def _one_frame(mav: Any, data: bytes) -> tuple[Any | None, int]:
    """(message or None, bytes it took) for a frame starting at data[0]."""
    _drop_partial_frame(mav)
    chunk = data[:MAX_FRAME]
    msg = mav.parse_char(chunk)
    if msg is None or msg.get_type() == "BAD_DATA":
        return None, 0
    return msg, max(1, len(chunk) - mav.buf_len())  # buf_len: what is left unparsed of the chunk


def _resync(mav: Any, data: bytes) -> list[Any]:
    """Every valid frame of a damaged datagram, trying each start byte in turn (junk before, between or
    after frames costs none of the good ones); the junk is reported as one BAD_DATA per run."""
    out: list[Any] = []
    pos, junk_from, tries = 0, None, 0
    while pos < len(data) and tries <= MAX_RESYNC:
        msg, used = _one_frame(mav, data[pos:]) if data[pos] in MAGIC else (None, 0)
        tries += data[pos] in MAGIC and msg is None
        if msg is None:
            junk_from = pos if junk_from is None else junk_from
            pos += 1
            continue
        if junk_from is not None:
            out.append(mavlink.MAVLink_bad_data(bytearray(data[junk_from:pos]), "junk between frames"))
            junk_from = None
        out.append(msg)
        pos += used
    if junk_from is not None or pos < len(data):
        start = junk_from if junk_from is not None else pos
        out.append(mavlink.MAVLink_bad_data(bytearray(data[start:]), "junk after the last frame"))
    _drop_partial_frame(mav)
    return out


def parse_datagram(mav: Any, data: bytes) -> list[Any]:
    """The messages (and BAD_DATA) of one UDP datagram: pymavlink's parse, and when that found nothing but
    damage, a frame-by-frame resync (so that junk holding a 0xFD byte cannot swallow the good frame after it)."""
    parsed = mav.parse_buffer(data) or []
    partial = mav.buf_len() > 0
    _drop_partial_frame(mav)
    damaged = [m for m in parsed if m.get_type() == "BAD_DATA"]
    framed = partial or any("CRC" in getattr(m, "reason", "") or "length" in getattr(m, "reason", "")
                            for m in damaged)
    if not framed or len(damaged) < len(parsed):
        # clean, refused by signing (decoding again would count it twice), or some frames decoded (never
        # decoded twice: signing would take the second for a replay)
        return parsed
    return _resync(mav, data)


class Link:
    def __init__(self, settings: LinkSettings) -> None:
        self.settings = settings
        self.sysid: int = settings.sysid if settings.sysid is not None else DEFAULT_SYSID
        self.learned = settings.sysid is not None  # the id is configured or learned, not the default
        self.conn: mavutil.mavfile | None = None
        self.policy = UnsignedPolicy() if settings.signing_key is not None else None
        self.opened_at = 0.0
        self.last_rx = 0.0
        self._next_try = 0.0
        self._delay = settings.retry_min
        self._ever_received = False
        self.sent = self.received = self.bad = self.opens = 0
        self._throttle = Throttle(log)

    # -- connection ---------------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self.conn is not None

    def fileno(self) -> int | None:
        if self.conn is None:
            return None
        fd = getattr(self.conn, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    @property
    def is_udp(self) -> bool:
        return isinstance(self.conn, mavutil.mavudp)

    def maintain(self, now: float) -> None:
        """Open when due; treat a silent serial or TCP link as lost (a silent UDP link only as quiet)."""
        if self.conn is None:
            if now >= self._next_try:
                self._open(now)
            return
        quiet_since = max(self.last_rx, self.opened_at)
        if now - quiet_since > self.settings.silence_timeout:
            if not self.is_udp:
                self.lost(now, f"no data for {self.settings.silence_timeout:g} s")
            else:
                self._throttle.log(
                    logging.WARNING, "quiet", "MAVLink %s: nothing received for %.0f s (still sending)",
                    self.settings.url, now - quiet_since, counted=False,
                )  # fmt: skip

    def _open(self, now: float) -> None:
        s = self.settings
        device, baud = split_device(s.url)
        try:
            conn = mavutil.mavlink_connection(
                device,
                baud=baud or 115200,
                source_system=self.sysid,
                source_component=s.component,
                dialect=s.dialect,
                autoreconnect=False,
                retries=0,
            )
        except Exception as exc:  # OSError, serial.SerialException, ValueError for a bad string
            self._next_try = now + self._delay
            self._throttle.log(logging.WARNING, "open", "cannot open MAVLink %s (%s); retrying", s.url, exc)
            self._delay = min(self._delay * 2, s.retry_max)
            return
        conn.robust_parsing = conn.mav.robust_parsing = True
        if isinstance(conn, mavutil.mavudp) and conn.udp_server:
            # pymavlink binds with SO_REUSEADDR; cleared once bound, a second program's bind to this port fails
            # instead of silently taking the ground station's traffic (Linux checks the flag at each bind)
            conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 0)
        if s.signing_key is not None:
            conn.setup_signing(
                s.signing_key, sign_outgoing=True, allow_unsigned_callback=self.policy, link_id=SIGNING_LINK_ID
            )
            conn.mav.check_signature = SignatureCheck(conn.mav.signing)
        self.conn, self.opened_at, self.opens = conn, now, self.opens + 1
        log.info("MAVLink %s open%s", s.url, " (signed)" if s.signing_key is not None else "")

    def lost(self, now: float, reason: str) -> None:
        """Close after a failure; the next `maintain` after the retry delay reopens."""
        if self.conn is not None:
            log.warning("MAVLink %s lost (%s); reconnecting", self.settings.url, reason)
            try:
                self.conn.close()
            except Exception:
                log.debug("close failed", exc_info=True)
        self.conn = None
        self._next_try = now + self._delay
        self._delay = min(self._delay * 2, self.settings.retry_max)

    def close(self) -> None:
        if self.conn is not None:
            try:
                self.conn.close()
            except Exception:
                log.debug("close failed", exc_info=True)
            self.conn = None

    # -- receive ------------------------------------------------------------------------------------
    def _tcp_closed(self) -> bool:
        """EOF or reset on a TCP link (pymavlink would print and spin on it instead)."""
        port = getattr(self.conn, "port", None)
        if not isinstance(self.conn, mavutil.mavtcp) or port is None:
            return False
        try:
            return port.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
        except (BlockingIOError, InterruptedError):
            return False

    def _messages(self, limit: int) -> list[Any]:
        conn = self.conn
        assert conn is not None
        if not isinstance(conn, mavutil.mavudp):
            msgs = []
            for _ in range(limit):
                msg = conn.recv_msg()
                if msg is None:
                    break
                msgs.append(msg)
            return msgs
        # UDP: parse each datagram on its own. pymavlink keeps an incomplete frame in its buffer and would
        # glue the next datagram to it, so one truncated or junk datagram would cost the next good packet.
        msgs = []
        for _ in range(limit):
            data = conn.recv()
            if not data:
                break
            for msg in parse_datagram(conn.mav, data):
                if msg.get_type() != "BAD_DATA":
                    conn.post_message(msg)
                msgs.append(msg)
        return msgs

    def receive(self, now: float, limit: int = 200) -> list[Any]:
        """Messages waiting now (at most `limit`); bad packets are counted and dropped."""
        if self.conn is None:
            return []
        out: list[Any] = []
        try:
            if self._tcp_closed():
                self.lost(now, "connection closed by peer")
                return out
            for msg in self._messages(limit):
                if msg.get_type() == "BAD_DATA":
                    self.bad += 1
                    reason = getattr(msg, "reason", "")
                    self._throttle.log(logging.WARNING, "bad", "dropped a bad MAVLink packet: %s", reason)
                    continue
                out.append(msg)
        except Exception as exc:
            self.lost(now, f"{type(exc).__name__}: {exc}")
            return out
        if out:
            self.last_rx = now
            self._delay = self.settings.retry_min
            if not self._ever_received:
                self._ever_received = True
                log.info("MAVLink %s receiving", self.settings.url)
        self.received += len(out)
        self._report_unsigned()
        return out

    def _report_unsigned(self) -> None:
        if self.policy is None:
            return
        rejected = self.policy.take_rejected()
        for msg_id, count in rejected.items():
            name = getattr(mavlink.mavlink_map.get(msg_id), "msgname", str(msg_id))
            self._throttle.log(
                logging.WARNING, f"unsigned{msg_id}", "rejected %d unsigned or badly signed %s", count, name
            )

    def adopt_sysid(self, sysid: int) -> bool:
        """Take the autopilot's system id as ours (once); False when a different one is configured or learned."""
        if not self.learned:
            self.learned = True
            if sysid != self.sysid:
                log.info("system id %d adopted from the autopilot heartbeat (was %d)", sysid, self.sysid)
            else:
                log.info("system id %d confirmed by the autopilot heartbeat", sysid)
            self.sysid = sysid
        if self.conn is not None:
            self.conn.mav.srcSystem = self.conn.source_system = self.sysid
        return self.sysid == sysid

    # -- send ---------------------------------------------------------------------------------------
    def send(self, msg: Any, now: float) -> bool:
        """Send one message; False (and nothing sent) without a connection."""
        if self.conn is None:
            return False
        mav = self.conn.mav
        mav.srcSystem, mav.srcComponent = self.sysid, self.settings.component
        try:
            mav.send(msg)
        except struct.error as exc:  # a value the message cannot carry, not a lost link: drop it, keep the link
            self._throttle.log(logging.ERROR, "pack", "%s not sent: %s", msg.get_type(), exc)
            return False
        except Exception as exc:
            self.lost(now, f"send failed: {type(exc).__name__}: {exc}")
            return False
        self.sent += 1
        return True

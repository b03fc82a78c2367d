"""MAVLink 2 signing: the shared key from a file, and the rule for unsigned packets once signing is on.

Key file formats, tried in this order:
- exactly 32 bytes: the raw key;
- 64 hexadecimal digits (surrounding whitespace ignored): the key in hex;
- anything else: a passphrase (UTF-8, surrounding whitespace stripped) whose SHA-256 digest is the key,
  the rule MAVProxy's `signing setup PASSPHRASE` uses, so one passphrase configures both ends.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import stat
import string
import threading
from collections import Counter
from pathlib import Path
from typing import Any

from dadiff.runtime.errors import DadiffError
from dadiff.runtime.user_files import SETTINGS_LIMIT, read_user_bytes

log = logging.getLogger(__name__)

KEY_BYTES = 32
RADIO_STATUS = 109  # SiK radios inject it unsigned; ArduPilot accepts it unsigned for the same reason


class SigningKeyError(DadiffError, ValueError):
    """The key file is missing, unreadable or empty (one-line message)."""


def key_from_bytes(data: bytes) -> bytes:
    """The 32-byte secret for a key file's contents (see the module docstring)."""
    if len(data) == KEY_BYTES:
        return data
    try:
        text = data.decode("utf-8").strip()
    except UnicodeDecodeError:
        raise SigningKeyError(f"expected 32 raw bytes, 64 hex digits or a passphrase, got {len(data)} bytes") from None
    if not text:
        raise SigningKeyError("the key file is empty")
    if len(text) == 2 * KEY_BYTES and all(c in string.hexdigits for c in text):
        return bytes.fromhex(text)
    return hashlib.sha256(text.encode("utf-8")).digest()


def load_key(path: Path) -> bytes:
    """Read the signing key; warns when the file is readable by group or others."""
    try:
        data = read_user_bytes(path, SETTINGS_LIMIT)
        mode = path.stat().st_mode
    except OSError as exc:
        raise SigningKeyError(f"{path}: cannot read signing key ({exc.strerror or exc})") from None
    if mode & (stat.S_IRGRP | stat.S_IROTH):
        log.warning("signing key %s is readable by other users (chmod 600 it)", path)
    try:
        return key_from_bytes(data)
    except SigningKeyError as exc:
        raise SigningKeyError(f"{path}: {exc}") from None


class SignatureCheck:
    """Stands in for pymavlink's `MAVLink.check_signature` on our connection.

    pymavlink records a stream's timestamp before it compares the signature, so one forged packet with a
    future timestamp and a ground station's source ids would lock the real ground station out until its
    clock passed the forgery. Here the timestamp counts only once the signature is right. Rules (MAVLink 2
    signing): the signature is the first 6 bytes of SHA-256(key + the frame up to the signature); a known
    stream (link id, system, component) must move its timestamp forward; a new one may be at most a
    minute behind ours.
    """

    NEW_STREAM_SLACK = 60 * 100_000  # one minute in the 10 µs units of signing timestamps

    def __init__(self, signing: Any) -> None:
        self.signing = signing

    def __call__(self, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        signing = self.signing
        if signing.secret_key is None or len(msgbuf) < 13:
            return False
        link_id = msgbuf[-13]
        timestamp = int.from_bytes(msgbuf[-12:-6], "little")
        digest = hashlib.sha256(bytes(signing.secret_key) + bytes(msgbuf[:-6])).digest()[:6]
        if not hmac.compare_digest(digest, bytes(msgbuf[-6:])):
            return False
        stream = (link_id, src_system, src_component)
        last = signing.stream_timestamps.get(stream)
        if last is not None and timestamp <= last:
            return False  # replayed or reordered
        if last is None and timestamp + self.NEW_STREAM_SLACK < signing.timestamp:
            return False
        signing.stream_timestamps[stream] = timestamp
        signing.timestamp = max(signing.timestamp, timestamp)
        return True


class UnsignedPolicy:
    """pymavlink's allow_unsigned_callback: with signing on, only RADIO_STATUS may come unsigned.

    Everything else unsigned, commands and the autopilot's heartbeat included, is dropped by the parser;
    the drops are counted per message id so that the service can log them.
    """

    def __init__(self) -> None:
        self._rejected: Counter[int] = Counter()
        self._lock = threading.Lock()

    def __call__(self, mav: object, msg_id: int) -> bool:
        if msg_id == RADIO_STATUS:
            return True
        with self._lock:
            self._rejected[msg_id] += 1
        return False

    def take_rejected(self) -> dict[int, int]:
        """Rejections since the last call, by message id."""
        with self._lock:
            out, self._rejected = dict(self._rejected), Counter()
        return out

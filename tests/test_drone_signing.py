"""MAVLink 2 signing: key files, and over loopback signed commands accepted, unsigned or wrongly signed ones
rejected (no ACK, nothing started)."""

from __future__ import annotations

import hashlib
import os
import time
from pathlib import Path

import pytest

from dadiff.drone.mav import mavlink
from dadiff.drone.signing import SignatureCheck, SigningKeyError, UnsignedPolicy, key_from_bytes, load_key
from drone_peers import GroundStation, Rig

KEY = hashlib.sha256(b"test flight").digest()
RECT = mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE


def test_key_formats(tmp_path: Path) -> None:
    raw = bytes(range(32))
    assert key_from_bytes(raw) == raw
    assert key_from_bytes((raw.hex() + "\n").encode()) == raw
    assert key_from_bytes(raw.hex().upper().encode()) == raw
    assert key_from_bytes(b"  correct horse battery\n") == hashlib.sha256(b"correct horse battery").digest()
    for bad in (b"", b"  \n", b"\xff\xfe\x00"):
        with pytest.raises(SigningKeyError):
            key_from_bytes(bad)
    path = tmp_path / "key"
    path.write_text(raw.hex())
    os.chmod(path, 0o600)
    assert load_key(path) == raw
    with pytest.raises(SigningKeyError, match="cannot read"):
        load_key(tmp_path / "missing")


def test_unsigned_policy() -> None:
    policy = UnsignedPolicy()
    assert policy(None, mavlink.MAVLINK_MSG_ID_RADIO_STATUS)
    assert not policy(None, mavlink.MAVLINK_MSG_ID_COMMAND_LONG)
    assert not policy(None, mavlink.MAVLINK_MSG_ID_COMMAND_LONG)
    assert not policy(None, mavlink.MAVLINK_MSG_ID_HEARTBEAT)
    assert policy.take_rejected() == {mavlink.MAVLINK_MSG_ID_COMMAND_LONG: 2, mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1}
    assert policy.take_rejected() == {}


def _signed(key: bytes, timestamp: int, src=(255, 190)) -> bytearray:
    sender = mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    sender.signing.secret_key, sender.signing.sign_outgoing = key, True
    sender.signing.link_id, sender.signing.timestamp = 3, timestamp
    msg = mavlink.MAVLink_command_long_message(1, 100, RECT, 0, 0.1, 0.1, 0.3, 0.3, 0, 0, 0)
    return bytearray(msg.pack(sender))


def test_forged_packet_does_not_lock_the_sender_out() -> None:
    receiver = mavlink.MAVLink(None)
    receiver.signing.secret_key, receiver.signing.timestamp = KEY, 100_000_000
    check = SignatureCheck(receiver.signing)
    good = _signed(KEY, 100_000_100)
    assert check(good, 255, 190)
    assert not check(good, 255, 190)  # replay
    assert not check(_signed(hashlib.sha256(b"x").digest(), 9_000_000_000), 255, 190)  # forged, far future
    assert check(_signed(KEY, 100_000_200), 255, 190)  # still accepted: the forgery moved nothing
    assert not check(_signed(KEY, 100_000_000 - 70 * 100_000, src=(254, 1)), 254, 1)  # new stream, too old


def test_signed_commands_only() -> None:
    with Rig(key=KEY) as rig:
        assert rig.connected()
        beat = rig.gcs.received("HEARTBEAT", src_component=100)[0].msg
        assert beat.get_signed()
        assert rig.gcs.call(mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION, 1).result == mavlink.MAV_RESULT_ACCEPTED
        for key in (None, hashlib.sha256(b"wrong").digest()):
            intruder = GroundStation(f"udpout:127.0.0.1:{rig.port}", key=key).start()
            try:
                assert intruder.call(RECT, 0.1, 0.1, 0.3, 0.3, timeout=1.0) is None  # dropped by the link
            finally:
                intruder.close()
        assert rig.tracker.inits == []
        assert rig.gcs.call(RECT, 0.1, 0.1, 0.3, 0.3).result == mavlink.MAV_RESULT_ACCEPTED
        assert rig.service.link.policy is not None
        # with signing on, every correctly signed sender may command, whatever its system id
        signed = GroundStation(f"udpout:127.0.0.1:{rig.port}", sysid=77, key=KEY).start()
        try:
            assert signed.call(RECT, 0.1, 0.1, 0.3, 0.3).result == mavlink.MAV_RESULT_ACCEPTED
        finally:
            signed.close()


def test_unsigned_autopilot_is_not_trusted() -> None:
    """With signing on, an unsigned autopilot heartbeat neither gives the system id nor arms the follower
    (the camera speaks first, signed, as system 1)."""
    with Rig(key=KEY, ap_key=b"") as rig:
        beat = rig.gcs.wait_for("HEARTBEAT", 1.5, where=lambda m: m.get_srcComponent() == 100)
        assert beat is not None and beat.get_signed() and beat.get_srcSystem() == 1
        time.sleep(0.3)
        assert not rig.service.link.learned and rig.service.loop.autopilot is None

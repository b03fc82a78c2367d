"""dadiff.drone: the tracker on a drone's companion computer, over MAVLink.

A camera component (QGroundControl's box → MAV_CMD_CAMERA_TRACK_RECTANGLE → tracker → 275 stream), an
optional follow controller (body-frame velocity setpoints in GUIDED / OFFBOARD) and the service that runs
both under systemd. Never imports torch, onnx or dadiff.export; importing this package loads nothing heavy.
"""

"""dadiff.drone: the tracker on a drone's companion computer, over MAVLink.

A camera component (QGroundControl's or MAVSDK's box → MAV_CMD_CAMERA_TRACK_RECTANGLE → tracker → 275
stream), optional following (body-frame velocity setpoints in GUIDED / OFFBOARD, or a gimbal through the
MAVLink gimbal manager) and the service that runs them under systemd. Never imports torch, onnx or
dadiff.export; importing this package loads nothing heavy.
"""

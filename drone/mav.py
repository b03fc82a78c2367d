"""The one import point for pymavlink: MAVLink 2 is forced before pymavlink first reads MAVLINK20.

`mavlink` holds the common dialect's constants and message classes; ids and enum values are the same in
ardupilotmega, which includes common, so they serve whichever dialect a connection speaks.
"""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

DIALECTS = ("ardupilotmega", "common")

__all__ = ["DIALECTS", "mavlink", "mavutil"]

"""MAVLink autopilots (PX4, ArduPilot) as units: the ``mavlink`` link kind and its pure parts.

- :mod:`.pymav`: the lazy pymavlink import (MAVLink 2, ardupilotmega dialect, a superset of common);
- :mod:`.poly`: exact conversion between our temperature polynomial and a shifted one;
- :mod:`.profiles`: each autopilot's gyro thermal-compensation parameters and their semantics;
- :mod:`.paramtx`: the parameter push as pure logic (PARAM_SET, echo, retries, read-back);
- :mod:`.imu`: IMU messages -> ``Sample`` and switch-on detection;
- :mod:`.state`: what the link must remember across restarts (versions, boot counts);
- :mod:`.link`: ``MavlinkLink``, the ``Link`` that ties them to a pymavlink connection.

docs/mavlink.md cites the autopilot sources each rule comes from.
"""

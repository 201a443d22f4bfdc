"""Camera sources and servo buses for real hardware (livebridge.drivers).

The URL schemes this package implements, as plain data for :mod:`livebridge.devices.registry` (nothing is
imported until a scheme is opened).
"""

CAMERA_SCHEMES = {
    "v4l2": "livebridge.drivers.v4l2:open_url",
    "depthai": "livebridge.drivers.depthai:open_url",
}

# scheme -> (opener, the facts the driver declares about its device family)
BUS_SCHEMES = {
    "dynamixel": ("livebridge.drivers.dynamixel:open_url", "livebridge.drivers.dynamixel:FACTS"),
    "maestro": ("livebridge.drivers.maestro:open_url", "livebridge.drivers.maestro:FACTS"),
    "ssc32": ("livebridge.drivers.ssc32:open_url", "livebridge.drivers.ssc32:FACTS"),
}

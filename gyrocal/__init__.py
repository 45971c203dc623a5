"""gyrocal: an on-line calibrator daemon for strapdown gyroscopes.

Units everywhere: deg/s for rates, g for specific force, degC for temperature, s for time.
"""

__version__ = "0.1.0"

"""pwm: shape modeling with integrated photogrammetry and pixel-weighted maplet photoclinometry."""

__version__ = "0.1.0"

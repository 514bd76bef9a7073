"""Viper field appliance: position from the skyline a camera sees, matched against a DEM."""

__version__ = "0.1.0"

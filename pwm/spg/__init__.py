"""Stereo photogrammetry: a starting shape and corrected poses from the images themselves."""

from pwm.spg.photogrammetry import PoseCorrection, SpgResult, stereo_photogrammetry

__all__ = ["PoseCorrection", "SpgResult", "stereo_photogrammetry"]

"""Stereo calibration of the camera rig (``iscd calibrate``)."""

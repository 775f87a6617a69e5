"""Stereo calibration of the camera rig (``iscd calibrate``).

Modules: ``io`` (the calibration file of SPEC section 7 and the geometry helpers the ranging
code uses), ``boards`` (chessboard / ChArUco targets), ``detect`` (corners, sub-pixel),
``solve`` (cv2.calibrateCamera + cv2.stereoCalibrate + cv2.stereoRectify, outlier rejection),
``verify`` (``--verify``), ``pipeline`` (image files -> observations), ``report`` (Markdown,
JSON, preview PNG), ``live`` (guided capture from the rig), ``synthetic`` (rendered boards
seen by a known rig, for tests). See docs/calibration.md.
"""

from iscd.calibration.io import (CalibrationError, StereoCalibration, load_calibration,
                            project_points, rectify_points, save_calibration)

__all__ = ["CalibrationError", "StereoCalibration", "load_calibration", "project_points",
           "rectify_points", "save_calibration"]

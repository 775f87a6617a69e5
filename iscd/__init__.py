"""iscd — image-sensor-communication daemon.

Decodes data sent by road LEDs (PWM-M, SPEC section 3) from two synchronized 1000 fps
cameras and measures the distance to them by stereo disparity, after the 2023
dissertation "Stereo-Vision-Based Simultaneous Visible Light Communication and Range
Estimation" (``../shared/seed``).
"""

__version__ = "0.1.0"

"""vmocap_core: the ROS-free mathematics of vmocap.

Markerless multi-camera motion capture after Ohashi et al., "Video Motion Capture from the
Part Confidence Maps of Multi-Camera Images by Spatiotemporal Filtering Using the Human
Skeletal Model". Nothing in this package imports rclpy.
"""

__version__ = "0.1.0"

"""MCAP bags without ROS: CDR codec, rosbag2-compatible reader/writer, message conversions."""

from .mcap_io import BagMessage, BagReader
from .writer import BagWriter

__all__ = ["BagMessage", "BagReader", "BagWriter"]

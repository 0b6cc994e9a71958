"""Thin rclpy nodes of the vmocap graph (all logic lives in vmocap_core)."""

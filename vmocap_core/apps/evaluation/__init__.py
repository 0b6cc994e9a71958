"""Evaluation on real data: the Shelf benchmark (multi-person, real OpenPose detections)."""

"""Exports of a processed session (`vmocap export`): BVH, C3D, TRC, CSV, and session plots."""

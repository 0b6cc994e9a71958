"""Rendering a textured human body performing a motion clip in a calibrated rig."""

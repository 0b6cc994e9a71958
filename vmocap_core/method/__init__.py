"""The spatiotemporal filter of the paper (section II), one stage per module, in the order a
frame set flows through them (see pipeline.py, which composes them)."""

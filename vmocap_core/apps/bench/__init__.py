"""Benchmark commands: they print figures (and JSON with --json); tests do not time things."""

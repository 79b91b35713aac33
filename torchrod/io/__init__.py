"""Readings in, records out: JSON lines and CSV, reading checks, streams."""

"""Capture sessions: a phone or robot capture aligned to a map and added to it."""

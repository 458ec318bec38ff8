"""A map measures itself: its own references localized against the rest of it."""

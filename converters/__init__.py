"""Converters: recorded traffic and synthetic traffic into MCAP scenes (the only MCAP writers)."""

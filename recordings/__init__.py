"""Recordings: results streamed into Rerun .rrd files (the only package that imports rerun)."""

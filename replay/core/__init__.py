"""The replay engine: frames through every model and the cascade, out to sinks; its tables and process pool."""

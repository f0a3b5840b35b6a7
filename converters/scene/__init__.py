"""The scene file: its format, schema, reader, writer, Foxglove channel and errors."""

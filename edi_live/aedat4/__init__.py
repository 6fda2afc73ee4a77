"""AEDAT 4.0 codec: streaming reader and writer (the only users of lz4 and zstandard)."""

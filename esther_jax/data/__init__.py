"""Data: clip folders (I/O of the formats in ARCHITECTURE.md)."""

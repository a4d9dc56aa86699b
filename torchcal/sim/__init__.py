"""The digital twin: a true robot with known errors, and instrument models that measure it."""

"""Scoring: pure functions of tracks and truth (errors, consistency, identity of nothing yet), shared
by ``metrics.json``, the report and the recording; nothing here reads or writes files."""

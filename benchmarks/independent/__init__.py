"""Independently written simulators for the diagnosis benchmark (issue 15 item 8)."""

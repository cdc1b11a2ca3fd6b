"""See base.py for the role interface."""

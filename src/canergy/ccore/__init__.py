"""The supervisor role compiled from firmware/ (C), for the host: see supervisor.py."""

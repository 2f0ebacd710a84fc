"""Authenticated mode: key files, per-node keys, SecOC-like MACs on canergy frames."""

"""Embedded client emulator (firmware style) — arrives with the live-CAN work.

Today the client's protocol rules live in ``canergy.core`` (``Client``, ``HardenedClient``), and the
emulator built here later must use them rather than copy them. Nothing in this package is
functional yet.
"""

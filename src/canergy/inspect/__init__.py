"""Inspection: describe frames, read captures, render candump-style lines, audit passivity."""

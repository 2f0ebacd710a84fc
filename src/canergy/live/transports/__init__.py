"""Transports beside each other (as python-can's ``interfaces/``): the python-can buses canergy
adds or wraps."""

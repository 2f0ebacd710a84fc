"""Helpers that test modules import (rigs, README recipes); not tests themselves."""

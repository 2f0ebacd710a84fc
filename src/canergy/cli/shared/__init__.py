"""Flag groups and helpers that several commands share."""

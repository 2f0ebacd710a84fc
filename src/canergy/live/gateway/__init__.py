"""A gateway process: the client above, the supervisor below, one record."""

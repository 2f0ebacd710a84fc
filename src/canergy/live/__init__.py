"""Live CAN: the bus loop, the supervisor service and its files, grant policies and limits."""

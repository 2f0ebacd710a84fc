"""Integration tests of nodes against a real supervisor: the pytest plugin (``plugin``, loaded
by pytest through the ``pytest11`` entry point ``canergy``), the supervisor it starts
(``supervisor``) and the books it closes at teardown (``books``). The fault-injecting bridge is
``canergy.bridge``."""

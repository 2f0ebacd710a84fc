"""``canergy monitor``: a live, full-screen view of the budgets on a bus or in a replayed capture.

``model`` rebuilds every node's transactions from the frames (``sessions``) and adds rates, bus
load (``busload``), decode errors and the supervisor's books (``books``); ``render`` turns a
snapshot into lines of text, ``view`` keeps what the user chose (filter, sort, selection),
``feeds`` brings frames in from a bus or a capture, and ``tui`` is the thin curses loop.
"""

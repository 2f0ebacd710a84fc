"""Passivity as a theorem (``canergy prove``, the ``prove`` extra: z3-solver): the hardened
rules as SMT terms (``symbolic``), tested cell by cell against the Python tables."""

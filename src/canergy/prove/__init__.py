"""Passivity as a theorem, in progress (issue 32; the ``prove`` extra: z3-solver): so far the
hardened rules of one session as SMT terms (``symbolic``), tested cell by cell against the
Python tables. The inductive invariant and ``canergy prove`` are to come."""

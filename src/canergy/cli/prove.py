"""``canergy prove``: the passivity theorem, every proof obligation checked by z3."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from collections.abc import Iterable
from typing import Any

from canergy.argtypes import bounded_int
from canergy.cli.summaries import SUMMARIES
from canergy.prove import CONFIRMED_BY, EFFORT, NARROWED, RULE_NAMES, TRACE_IN_TESTS


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "prove",
        help=SUMMARIES["prove"],
        description=(
            "Check with z3 that an inductive invariant of one supervisor session and its "
            "client, with any set of frames in flight (lost, duplicated, reordered, delayed), "
            "power losses and lost books of either side, holds initially, is kept by every cell "
            "of the rules and implies the ledger with dissipation >= 0: passivity for any "
            "number of transactions, counters as bit-vectors of their real widths. Prints each "
            "obligation (step x clause) with its result and time; exit 1 with a counterexample "
            "to induction when one fails. Assumptions: docs/protocol.md, 'Passivity as a "
            "theorem'. Needs canergy[prove] (z3-solver)."
        ),
    )
    p.add_argument(
        "--rules",
        choices=RULE_NAMES,
        default="hardened",
        help=(
            "the rule set (default hardened); witnessed (with both restore steps) proves "
            "under assumption 2 narrowed; the others are unsound and must fail"
        ),
    )
    p.add_argument(
        "--keep-going",
        action="store_true",
        help="check every obligation after a failure (default: stop at the first)",
    )
    p.add_argument(
        "--effort",
        type=bounded_int(1_000_000, 10**12),
        default=EFFORT,
        metavar="STEPS",
        help=(
            "z3's resource limit per check (its rlimit: where a check stops does not depend "
            "on the machine's speed or load); reaching it leaves the obligation undecided, "
            f"which fails the run (default {EFFORT:,})"
        ),
    )
    p.add_argument(
        "--timeout",
        type=bounded_int(1, 86_400),
        metavar="SECONDS",
        help=(
            "also stop each check after this long (default: no wall-clock limit); what fails "
            "then depends on the machine and its load"
        ),
    )
    p.add_argument(
        "--step",
        action="append",
        default=[],
        type=str,
        metavar="NAME",
        help=(
            "check only this step's obligations (repeatable; the initial state and the "
            "conclusion are left out); an unknown name lists the steps of the rules"
        ),
    )
    p.add_argument("-q", "--quiet", action="store_true", help="print failures and the summary only")
    p.add_argument("--json", metavar="FILE", help="write every obligation's result as JSON")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from canergy.extras import require

    require("prove")
    from canergy.prove.obligations import cases, check_all
    from canergy.prove.rules import RULES
    from canergy.prove.symbolic import z3

    names = [case.name for case in cases(RULES[args.rules])]
    unknown = [name for name in args.step if name not in names]
    if unknown:
        listed = "\n".join(f"  {name}" for name in names)
        print(
            f"canergy prove: error: no step {unknown[0]!r} in the {args.rules} rules; "
            f"its steps:\n{listed}",
            file=sys.stderr,
        )
        return 2
    with contextlib.ExitStack() as stack:  # a report that cannot be written fails at once
        report = stack.enter_context(open(args.json, "w")) if args.json else None
        print(f"{args.rules} rules, z3 {z3.get_version_string()}")
        started = time.perf_counter()
        timeout_ms = None if args.timeout is None else args.timeout * 1000
        outcomes = check_all(RULES[args.rules], timeout_ms, args.step, args.effort)
        done, failed = _check(outcomes, args)
        elapsed = time.perf_counter() - started
        if report is not None:
            json.dump([vars(o) for o in done], report, indent=1)
    if not failed and args.step:
        print(
            f"{len(done)} obligations of {len(set(args.step))} step(s) proved in "
            f"{elapsed:.1f} s: these steps only, not the theorem (run without --step for it)"
        )
        return 0
    if not failed:
        print(f"{len(done)} obligations proved in {elapsed:.1f} s: no step creates energy")
        if args.rules in NARROWED:
            print(f"under {NARROWED[args.rules]}")
        return 0
    undecided = [o for o in failed if o.undecided]
    if undecided:
        print(
            f"{len(undecided)} of {len(done)} obligations checked were not decided within "
            f"{_limits(args)} in {elapsed:.1f} s: neither proved nor refuted (raise the limit)",
            file=sys.stderr,
        )
    if len(undecided) < len(failed):
        print(
            f"{len(failed) - len(undecided)} of {len(done)} obligations checked failed in "
            f"{elapsed:.1f} s: the invariant is not inductive under these rules",
            file=sys.stderr,
        )
    commands = CONFIRMED_BY.get(args.rules, ())
    for command in commands:
        print(f"the bounded checker finds a real trace: {command}", file=sys.stderr)
    if args.rules in CONFIRMED_BY and not commands:
        print(f"the bounded checker finds a real trace: {TRACE_IN_TESTS}", file=sys.stderr)
    return 1


def _limits(args: argparse.Namespace) -> str:
    """The limits a check ran under, as flags."""
    timeout = "" if args.timeout is None else f" or --timeout {args.timeout}"
    return f"--effort {args.effort:,}{timeout}"


def _check(outcomes: Iterable[Any], args: argparse.Namespace) -> tuple[list[Any], list[Any]]:
    """Print each obligation as it is checked; stop at the first failure unless told not to."""
    done: list[Any] = []
    failed: list[Any] = []
    for outcome in outcomes:
        done.append(outcome)
        mark = "proved" if outcome.proved else "UNDECIDED" if outcome.undecided else "FAILED"
        if not (args.quiet and outcome.proved):
            print(f"  {mark}  {outcome.seconds:7.2f} s  {outcome.step}: {outcome.clause}")
        if not outcome.proved:
            failed.append(outcome)
            print(outcome.counterexample)
            if not args.keep_going:
                break
    return done, failed

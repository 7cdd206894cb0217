"""The command line of :mod:`torcsrl.policies` (``python -m torcsrl.policies``): ``export CKPT OUT`` writes a policy
file (what the shipped reference driver is), ``ensemble OUT A B ... --reduce cautious [--side-guard C[:G[:E]]]`` an
ensemble file, ``member FILE I OUT`` one member of an ensemble file, and ``info SPEC`` prints what a spec loads."""

from __future__ import annotations

import argparse
import sys

from torcsrl.policies.base import PolicyError
from torcsrl.policies.checkpoint import export_policy
from torcsrl.policies.files import export_ensemble, export_member
from torcsrl.policies.guard import SideGuard, parse_guard_values
from torcsrl.policies.registry import load_policy

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torcsrl.policies", description="Inspect or export evaluation policies.")
    sub = parser.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="write a policy file (actor weights + config) from a training checkpoint")
    e.add_argument("checkpoint")
    e.add_argument("out")
    en = sub.add_parser("ensemble", help="write ONE policy file driving several checkpoints as an ensemble (EnsemblePolicy)")
    en.add_argument("out")
    en.add_argument("checkpoints", nargs="+")
    en.add_argument("--reduce", default="mean", help="mean, median, cautious, medoid or guarded[:<m>] (EnsemblePolicy)")
    en.add_argument("--side-guard", default=None, metavar="CLEAR_M[:GAIN[:EDGE]]",
                    help="drive the file behind a SideGuard with these settings (e.g. 2.6; defaults for the rest)")
    mb = sub.add_parser("member", help="write one member of an ensemble file as a one-actor policy file (e.g. for init.actor)")
    mb.add_argument("ensemble")
    mb.add_argument("index", type=int)
    mb.add_argument("out")
    i = sub.add_parser("info", help="print what a policy spec loads")
    i.add_argument("spec")
    args = parser.parse_args(argv)
    try:
        if args.cmd == "export":
            out = export_policy(args.checkpoint, args.out)
            print(f"wrote {out} ({out.stat().st_size / 1024:.0f} KiB)")
        elif args.cmd == "ensemble":
            guard = None if args.side_guard is None else parse_guard_values(args.side_guard)
            out = export_ensemble(args.checkpoints, args.out, args.reduce, guard=guard)
            pol = load_policy(out)
            print(f"wrote {out} ({out.stat().st_size / 1024:.0f} KiB): {len(args.checkpoints)} members, reduce={args.reduce}"
                  + (f", side guard {pol.settings}" if isinstance(pol, SideGuard) else ""))
        elif args.cmd == "member":
            out = export_member(args.ensemble, args.index, args.out)
            print(f"wrote {out} ({out.stat().st_size / 1024:.0f} KiB): member {args.index} of {args.ensemble}")
        else:
            print(load_policy(args.spec).describe())
    except PolicyError as err:
        print(f"torcsrl.policies: error: {err}", file=sys.stderr)
        return 2
    return 0

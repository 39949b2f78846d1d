"""Fuzz ``fgslam replay``: mutated raw recordings must be decoded or refused in one line.

A valid raw directory of a short simulated run (``fuzzlib.simulated_recording``) is mutated
``--n`` times, one file each time (``fuzzlib.mutated_recordings``: byte flips, truncation,
garbage, hostile header and marker fields, re-signed records with hostile times or bytes), and
each mutant is replayed through ``fgslam.cli.main``. Prints how many were decoded, refused
(exit 2, one error line) or ended otherwise (a traceback: its exception and place), by kind
of mutation.

Run: python experiments/fuzz_raw.py [--n 10000] [--seed 0] [--duration 3]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections import Counter
from pathlib import Path

import fuzzlib


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000, help="mutants (default 10000)")
    ap.add_argument("--seed", type=int, default=0, help="mutation seed (default 0)")
    ap.add_argument("--duration", type=float, default=3.0, help="simulated s (default 3)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        raw = fuzzlib.simulated_recording(Path(tmp) / "raw", args.duration, args.seed)
        base = fuzzlib.replay_outcome(raw, Path(tmp) / "base.log")
        if base.kind != "decoded":
            raise SystemExit(f"the unmutated recording does not replay: {base}")
        originals = {p.name: p.read_bytes() for p in raw.iterdir()}
        kinds: Counter[str] = Counter()
        by_mutation: Counter[tuple[str, str]] = Counter()
        escapes: Counter[str] = Counter()
        examples: dict[str, str] = {}
        out = Path(tmp) / "out.log"
        mutants = fuzzlib.mutated_recordings(raw, args.n, args.seed)
        for name, what, data in mutants:
            (raw / name).write_bytes(data)
            res = fuzzlib.replay_outcome(raw, out)
            (raw / name).write_bytes(originals[name])
            kinds[res.kind] += 1
            first = what.split(":")[0]
            by_mutation[(first, res.kind)] += 1
            if res.kind in ("traceback", "odd"):
                escapes[res.detail.split(":")[0]] += 1
                examples.setdefault(res.detail.split(":")[0], f"{name}: {what} -> {res.detail}")
    print(
        f"{args.n} mutants of a {args.duration:g} s recording, seed {args.seed}, "
        f"{time.perf_counter() - t0:.0f} s"
    )
    print("| outcome | mutants |\n|---|---|")
    for k in ("decoded", "refused", "traceback", "odd"):
        print(f"| {k} | {kinds[k]} |")
    print("\n| first mutation | outcome | mutants |\n|---|---|---|")
    for (m, k), c in sorted(by_mutation.items()):
        print(f"| {m} | {k} | {c} |")
    for k, c in escapes.most_common():
        print(f"\n{c} x {k}\n  e.g. {examples[k]}")


if __name__ == "__main__":
    main()

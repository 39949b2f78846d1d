"""iSAM2's settings measured (issue 33, item 3): the ``[graph]`` section's relinearisation
threshold and skip, the updates after a loop closure, the refresh period and the
factorisation, each changed alone from the defaults, on a real log: CPU of the whole run and
of the backend's commits, the relations error of the every-scan trajectory, the loops
accepted, the keyframes, and the guard's repairs (a factorisation that refused a keyframe).

Run: python experiments/bench_isam2_settings.py [--log mit-csail] [--max-scans N]
Each setting runs in this process, one after the other, after an untimed warm-up (numba's
kernels loaded); CPU is the process clock. The log and its relations come from
``../shared/data`` as in ``bench_real_speed.py``, with the same scan-matching defaults.
"""

from __future__ import annotations

import argparse
import time

from bench_real_speed import DATA, FILES, RELATIONS, SCAN, relations
from real_carmen import limited

from fgslam.config import with_options
from fgslam.io.formats import open_log
from fgslam.slam.graph import GraphBackend
from fgslam.slam.runner import run_backends

# (label, [graph] keys changed from the defaults)
SETTINGS = [
    ("defaults (threshold 0.1, skip 10, QR)", {}),
    ("relinearize_threshold 0.05", {"relinearize_threshold": 0.05}),
    ("relinearize_threshold 0.2", {"relinearize_threshold": 0.2}),
    ("relinearize_skip 1", {"relinearize_skip": 1}),
    ("relinearize_skip 30", {"relinearize_skip": 30}),
    ("loop_updates 0", {"loop_updates": 0}),
    ("refresh_every 30", {"refresh_every": 30}),
    ("factorization CHOLESKY", {"factorization": "CHOLESKY"}),
]


def one(log: str, graph: dict, max_scans: int | None) -> dict:
    reader = open_log(DATA / FILES[log])
    cfg = with_options(reader.config, {"scanmatch": SCAN, "graph": graph})
    spent = [0.0]
    commit = GraphBackend.commit

    def timed(self):
        t0 = time.process_time()
        try:
            return commit(self)
        finally:
            spent[0] += time.process_time() - t0

    GraphBackend.commit = timed
    try:
        t0 = time.process_time()
        res = run_backends(limited(reader, max_scans), cfg, ["isam2"], "laser")[0]
        cpu = time.process_time() - t0
    finally:
        GraphBackend.commit = commit
    rel = relations(log, res) if max_scans is None and log in RELATIONS else None
    return {
        "cpu": cpu,
        "commit": spent[0],
        "log_s": res.log_duration,
        "rel": rel,
        "loops": sum(bool(c["accepted"]) for c in res.loop_closures),
        "keyframes": len(res.times),
        "repairs": len(res.stats.get("graph_repair_log", [])),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--log", default="mit-csail", choices=sorted(FILES))
    ap.add_argument("--max-scans", type=int, default=None)
    args = ap.parse_args()
    one(args.log, {}, 40)  # warm-up: numba's kernels from their cache
    print(
        "| setting | CPU (s) | real time / CPU | commits CPU (s) | relations m / deg | "
        "loops accepted | keyframes | repairs |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for label, graph in SETTINGS:
        r = one(args.log, graph, args.max_scans)
        rel = "{:.4f} / {:.3f}".format(*r["rel"]) if r["rel"] else "-"
        print(
            f"| {label} | {r['cpu']:.1f} | {r['log_s'] / r['cpu']:.1f}x | {r['commit']:.1f} | "
            f"{rel} | {r['loops']} | {r['keyframes']} | {r['repairs']} |",
            flush=True,
        )


if __name__ == "__main__":
    main()

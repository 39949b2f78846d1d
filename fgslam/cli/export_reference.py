"""``fgslam export-reference``: a log's truth or reference poses as a TUM trajectory."""

from __future__ import annotations

import argparse

from fgslam.cli.common import add_log_arguments, reader_options, reader_warnings
from fgslam.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export-reference",
        help="write a log's truth or reference poses as a TUM trajectory (for evo)",
        description=(
            "Write the ground truth of a simulated log, or the reference poses of a corrected "
            "CARMEN log, as a TUM trajectory (timestamp x y z qx qy qz qw), e.g. for evo: "
            "`evo_ape tum ref.tum out/trajectory.tum`."
        ),
    )
    add_log_arguments(p, "FILE.tum", "TUM file to write", tolerant=True)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fgslam.evaluation.metrics import write_tum
    from fgslam.events import TruthPose
    from fgslam.io.formats import open_log
    from fgslam.io.safeio import atomic_path

    reader = open_log(args.log, **reader_options(args))
    t: list[float] = []
    poses: list[tuple[float, float, float]] = []
    backwards = 0
    for ev in reader:
        if isinstance(ev, TruthPose):
            if t and ev.t < t[-1]:
                backwards += 1
                continue
            t.append(ev.t)
            poses.append((ev.x, ev.y, ev.theta))
    if not t:
        raise UserError(f"{args.log}: the log has no truth or reference poses")
    kind = reader.reference_kind or "ground truth"
    with atomic_path(args.out) as tmp:
        write_tum(tmp, t, poses)
    print(f"wrote {args.out}: {len(t)} poses ({kind}) over {t[-1] - t[0]:.1f} s")
    if backwards:
        print(f"left out {backwards} poses stamped earlier than the one before them")
    for w in reader_warnings(reader):  # the reader's, as every command prints them
        print(f"warning: {w}")
    return 0

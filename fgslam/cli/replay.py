"""``fgslam replay``: decode a raw device recording into a log."""

from __future__ import annotations

import argparse

from fgslam.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="decode a raw device recording into a log",
        description=(
            "Decode a raw recording (every byte the laser, sonar and odometry drivers received, "
            "timestamped: RAW_DIR/*.raw, as written by an online run with --record) through the "
            "drivers' own decoders into the native log (docs/log-format.md; '.gz' to "
            "compress). The same recording always gives the same log. Formats: "
            "docs/devices.md."
        ),
    )
    p.add_argument("raw_dir", metavar="RAW_DIR", help="directory of a raw recording")
    p.add_argument("--out", required=True, metavar="FILE.log", help="log file to write")
    p.add_argument(
        "--config", metavar="ROBOT.toml", help="robot configuration (default: the recorded one)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from fgslam.config import load_config, override_config
    from fgslam.online.ports import replay_to_log, session_config

    cfg = None
    if args.config:  # key by key over the recorded configuration (or the built-in one)
        cfg = override_config(session_config(args.raw_dir) or load_config(), args.config)
    with tqdm(desc="replaying", unit=" events", disable=None, leave=False) as bar:
        try:
            res = replay_to_log(args.raw_dir, args.out, cfg, progress=lambda _t: bar.update())
        except OSError as exc:
            raise UserError(f"cannot write {args.out}: {exc.strerror or exc}") from None
    kinds = ", ".join(f"{n} {k}" for k, n in sorted(res.by_kind.items())) or "no events"
    print(f"wrote {args.out}: {res.events} events ({kinds}) from {args.raw_dir}")
    for name, c in res.files.items():
        counts = ("crc_errors", "dropped_frames")
        notes = [f"{c[k]} {k.replace('_', ' ')}" for k in counts if c.get(k)]
        if c["truncated"]:
            notes.append("last record truncated")
        if c["skipped_bytes"]:
            notes.append(f"{c['skipped_bytes']} damaged bytes skipped")
        if notes:
            print(f"  {name}: {', '.join(notes)}")
    if res.rejected:
        print(f"  {res.rejected} measurements not usable (bad status, wrong beam count, faults)")
    return 0

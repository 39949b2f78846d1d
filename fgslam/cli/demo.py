"""``fgslam demo``: simulate the paper's corridor run and compare all backends."""

from __future__ import annotations

import argparse
from pathlib import Path

from fgslam.cli.common import progress_bar
from fgslam.cli.compare import compare_all


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="simulate the paper's corridor run and compare all backends (a few minutes)",
        description=(
            "Simulate the built-in corridor run (the paper's experiment) and run `fgslam "
            "compare` on it in the paper's scheme (wheel odometry, every scan a keyframe: "
            "`--odometry wheels --keyframes every-scan --loops off`): EKF vs iSAM2 vs batch, "
            "fused vs laser-only vs sonar-only."
        ),
    )
    p.add_argument(
        "--out",
        default="fgslam-demo",
        metavar="DIR",
        help="output directory (default ./fgslam-demo)",
    )
    p.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import time

    from fgslam.config import load_config
    from fgslam.sim import simulate_to_log
    from fgslam.sim.scenes import PAPER
    from fgslam.sim.world import load_world

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "corridor.log.gz"
    t0 = time.perf_counter()
    bar = progress_bar("simulating")
    try:
        run = simulate_to_log(load_world("corridor"), load_config(), log, args.seed, progress=bar)
    finally:
        bar.close()
    print(f"simulated the corridor run: {run.duration:.0f} s, {run.distance:.0f} m -> {log}")
    # the paper's experiment in the paper's scheme (wheel odometry, every scan a keyframe);
    # `fgslam compare` on the log runs the scan-matching defaults
    compare_all(str(log), str(out), None, sections={"scanmatch": dict(PAPER)})
    print((out / "comparison.md").read_text(), end="")
    print(
        f"demo done in {time.perf_counter() - t0:.0f} s: see {out}/comparison.png and "
        f"{out}/<backend>-<sensors>/map.png"
    )
    return 0

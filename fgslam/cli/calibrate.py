"""``fgslam calibrate``: its parser and command are
:func:`fgslam.evaluation.calibrate.add_parser` and
:func:`fgslam.evaluation.calibrate.calibrate_command`."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    from fgslam.evaluation.calibrate import add_parser

    add_parser(sub)

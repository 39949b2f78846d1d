"""The one reader interface (docs/readers.md, "One interface for every format").

Every sensor log :func:`fgslam.io.formats.open_log` opens (a native fgslam log, a CARMEN log,
a ROS bag) is a :class:`LogSource`: events by iteration, ``config``, ``world``, ``meta``,
``reference_kind``, the clock used (``clock``, ``clock_record``) and what went wrong in one
:class:`Problems`. Callers use only these; they never ask which format they hold.

:class:`Problems` is the same type for every reader: what was skipped (by reason), ignored
(record types the reader does not use), stamped backwards (by stream), the plausibility
findings (:class:`fgslam.io.readers.plausibility.Findings`: counts by kind, and under
``strict`` the first finding refused as :class:`~fgslam.io.readers.plausibility.ImplausibleInput`),
the one-line warnings and the ``report.json`` section. :class:`Source` is the base of the
foreign readers: a reader implements :meth:`Source.events` and iterating it applies the
plausibility rules; the native :class:`fgslam.io.logfile.LogReader` implements the interface
on its own (it streams in constant memory and knows the line of each record).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from os import PathLike
from typing import Any, Protocol, runtime_checkable

from fgslam.config import RobotConfig
from fgslam.events import Event
from fgslam.io.readers.plausibility import KINDS, Findings, Rules, check_events
from fgslam.io.readers.sanity import INDEX_PERIOD, OdometryLimits

StrPath = str | PathLike[str]
MAX_PROBLEMS = 20  # messages kept


def clock_warnings(clock: dict[str, Any] | None) -> list[str]:
    """The one-line warning of a log read in record order for want of a usable clock
    (``clock``: the record of :func:`fgslam.io.readers.sanity.choose_clock`), or none."""
    if not clock or not clock.get("fallback"):
        return []
    return [
        f"{clock['fallback']}: read in record order, scans {INDEX_PERIOD:g} s apart "
        "(--timestamps index), odometry speeds not checked; --strict refuses such a log"
    ]


class Problems:
    """What a reader skipped or found odd: one type for every reader.

    ``skipped_by_reason``: records not turned into events, by reason (``"unknown record
    NEFF"``, ``"bad FLASER record"``, ``"implausible odometry"``, ...), the first
    :data:`MAX_PROBLEMS` messages in ``messages``; ``ignored``: those of record types the
    reader does not use (CARMEN ``NEFF``, ...: no data lost; also in ``skipped_by_reason``);
    ``backwards``: records stamped earlier than the one before them, by stream; ``notes``:
    what the reader records of its set-up and pass (``"timestamps"``: the clock record,
    ``"odometry"``, ``"warnings"``); ``findings``: the plausibility findings of the current
    pass (:class:`~fgslam.io.readers.plausibility.Findings`), which hold ``strict``.

    Two properties of the reader say how its problems are reported, so that no caller asks
    for the format: ``passes_out_of_order`` (records stamped out of order are passed on as
    stamped, for the pipeline's reorder buffer, rather than dropped or carried by the
    reader: a native log) and ``report_keys`` (the keys of :meth:`summary` that make the
    reader's section of ``report.json``; None: all of it)."""

    def __init__(
        self, *, passes_out_of_order: bool = False, report_keys: tuple[str, ...] | None = None
    ) -> None:
        self.skipped_by_reason: Counter[str] = Counter()
        self.ignored: Counter[str] = Counter()
        self.backwards: Counter[str] = Counter()
        self.messages: list[str] = []
        self.notes: dict[str, Any] = {}  # e.g. "timestamps", "odometry" (docs/readers.md)
        self.findings: Findings | None = None
        self.passes_out_of_order = passes_out_of_order
        self.report_keys = report_keys

    @property
    def skipped(self) -> int:
        return sum(self.skipped_by_reason.values())

    @property
    def strict(self) -> bool:
        """Whether the first plausibility finding is refused (``--strict``)."""
        return self.findings is not None and self.findings.strict

    def new_pass(self) -> None:
        """Forget the counts of an earlier pass over the events (a reader read again counts
        each record once); the notes of the reader's set-up stay."""
        self.skipped_by_reason.clear()
        self.ignored.clear()
        self.backwards.clear()
        self.messages.clear()

    def skip(self, reason: str, message: str | None = None) -> None:
        """A record not turned into an event: counted by ``reason``, ``message`` kept."""
        self.skipped_by_reason[reason] += 1
        if message and len(self.messages) < MAX_PROBLEMS:
            self.messages.append(message)

    def ignore(self, reason: str) -> None:
        """A record of a type the reader does not use: skipped, and counted as ignored."""
        self.skip(reason)
        self.ignored[reason] += 1

    def note(
        self, kind: str, detail: str, *, line: int | None = None, skipped: bool = False
    ) -> None:
        """A plausibility finding of ``kind`` (:data:`fgslam.io.readers.plausibility.KINDS`)
        noted by the reader where it judges a rule at reading (with ``strict``, an
        :class:`~fgslam.io.readers.plausibility.ImplausibleInput`)."""
        assert self.findings is not None, "a finding outside a pass over the events"
        self.findings.note(kind, detail, line=line, skipped=skipped)

    def backward(self, stream: str, detail: str, line: int | None = None) -> None:
        """A record of ``stream`` stamped before the last one delivered (``detail`` names it),
        dropped or its motion carried by the reader: counted in ``backwards`` and noted as a
        stamp out of order (:mod:`fgslam.io.readers.plausibility`; with ``--strict`` an
        error)."""
        if self.findings is not None:
            self.findings.note("order", detail, line=line)
        self.backwards[stream] += 1

    def counts(self) -> dict[str, int]:
        """The plausibility findings by kind (``report.json`` keys, 0 for a kind not found)."""
        found = self.findings.counts if self.findings is not None else {}
        return {k.key: int(found.get(kind, 0)) for kind, k in KINDS.items()}

    def warnings(self) -> list[str]:
        """The one-line warnings for the console and ``report.json``: the reader's own (the
        clock, the input, the odometry), then one per kind of plausibility finding."""
        own = self.notes.get("warnings")
        out = list(own) if own is not None else clock_warnings(self.notes.get("timestamps"))
        if self.findings is not None:
            out += self.findings.warnings()
        return out

    def summary(self) -> dict[str, Any]:
        out = {
            "skipped": self.skipped,
            "skipped_by_reason": dict(self.skipped_by_reason),
            "timestamps_backwards": dict(self.backwards),
            "problems": list(self.messages),
            **self.notes,
        }
        if self.findings is not None:  # one warning per kind of implausible record
            out["plausibility"] = self.findings.summary()
            out["warnings"] = self.warnings()
        return out

    def report(self) -> dict[str, Any] | None:
        """The reader's section of ``report.json`` (``"reader"``), or None when it has none
        to give (a native log read without checks)."""
        summary = self.summary()
        if self.report_keys is None:
            return summary
        if "timestamps" not in summary and "plausibility" not in summary:
            return None
        return {k: summary[k] for k in self.report_keys if k in summary}


@runtime_checkable
class LogSource(Protocol):
    """What every sensor-log reader offers (``open_log`` returns one). ``reference_kind``:
    what its ``TruthPose`` events are, ``"ground truth"``, ``"reference"`` (a SLAM result
    such as a corrected CARMEN log's poses) or None (the format does not say: a native log's
    truth is the simulator's). ``clock``: the clock used (``"index"``: record order, no
    clock); ``clock_record``: what the clock check found and chose (docs/readers.md,
    "Timestamps"), None when the clock was not checked. ``strict``: refuse what is
    otherwise read with a warning."""

    format: str
    name: str
    config: RobotConfig
    world: str
    meta: dict[str, Any]
    reference_kind: str | None
    problems: Problems
    strict: bool
    clock: str | None

    @property
    def clock_record(self) -> dict[str, Any] | None: ...

    def __iter__(self) -> Iterator[Event]: ...

    def summary(self) -> dict[str, Any]: ...

    def close(self) -> None: ...

    def __enter__(self) -> Any: ...

    def __exit__(self, *exc: object) -> None: ...


class Source:
    """The base of the foreign readers, a :class:`LogSource`: ``config``, ``world``, ``meta``,
    ``reference_kind``, events by iteration; ``problems`` counts what was skipped. The
    attributes ``skipped`` and ``skipped_by_reason`` mirror ``problems``.

    A reader implements :meth:`events`; iterating the source passes them through the
    plausibility rules (:func:`fgslam.io.readers.plausibility.check_events`, with the reader's
    configuration, ``limits`` and ``clock``), the findings of the pass in
    ``problems.findings`` (with ``strict`` the first is an error)."""

    format = "?"
    config: RobotConfig
    world: str = ""
    reference_kind: str | None = None
    strict = False  # refuse what is otherwise read with a warning (--strict)
    clock: str | None = None  # the clock used, once chosen
    limits: OdometryLimits | None = None

    def __init__(self, path: StrPath) -> None:
        self.path = path
        self.name = str(path)
        self.meta: dict[str, Any] = {}
        self.problems = Problems()

    @property
    def clock_record(self) -> dict[str, Any] | None:
        return self.meta.get("timestamps")

    @property
    def skipped(self) -> int:
        return self.problems.skipped

    @property
    def skipped_by_reason(self) -> dict[str, int]:
        return dict(self.problems.skipped_by_reason)

    def summary(self) -> dict[str, Any]:
        """``problems.summary()``."""
        return self.problems.summary()

    def __iter__(self) -> Iterator[Event]:
        rules = Rules.of(self.config, self.limits, self.clock != "index")
        findings = Findings(self.name, self.strict, self.problems.skip, rules)
        self.problems.findings = findings
        return check_events(self.events(), rules, findings)

    def events(self) -> Iterator[Event]:
        """The reader's events of one pass, unchecked."""
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

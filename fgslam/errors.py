"""Errors that are the user's input, not the program's: the CLI prints them as one line."""


class UserError(Exception):
    """Bad input (file, option, data); the message is complete and meant for the user."""


class EvaluationError(UserError, ValueError):
    """Trajectories that cannot be compared as given: shapes that differ, too few poses to
    align, non-finite or overflowing values. A ValueError too, for callers that catch that."""


class ReaderError(UserError, ValueError):
    """A foreign log cannot be read; the message is one line naming file (and line)."""


class OutputWarning(UserWarning):
    """An output of a run (a file) that could not be written; the others were. The CLI shows
    it as one line naming the output and the cause."""


class RunWarning(UserWarning):
    """Something odd that a run survived (a repaired graph, a covariance that could not be
    computed): the CLI shows it as one line; report.json lists it."""

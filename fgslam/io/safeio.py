"""Outputs that are never half-written and never an input: atomic file writes (a temporary file
in the same folder, renamed over the target when complete) and the checks the CLI makes on
``--out`` before any work starts."""

from __future__ import annotations

import contextlib
import json
import os
import secrets
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from fgslam.errors import UserError


def temp_path(path: str | os.PathLike[str]) -> Path:
    """A fresh hidden name in ``path``'s folder that ends like ``path`` (``.log.gz``, ``.png``),
    so writers that choose compression or format by the name do the same for it."""
    p = Path(path)
    return p.with_name(f".tmp-{secrets.token_hex(4)}-{p.name[-200:]}")  # within NAME_MAX


def is_special(path: str | os.PathLike[str]) -> bool:
    """True for an existing target that is not a regular file (``/dev/null``, a FIFO): it is
    written in place, never replaced by a rename."""
    p = Path(path)
    return p.exists() and not p.is_file() and not p.is_dir()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path`` in one rename, on an
    exception it is deleted (``path`` is left as it was). A special file (``/dev/null``) is
    written in place."""
    if is_special(path):
        yield Path(path)
        return
    tmp = temp_path(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_json(path: str | os.PathLike[str], data: Any, indent: int | None = 2) -> None:
    """Write ``data`` as JSON to ``path`` atomically."""
    write_text(path, json.dumps(data, indent=indent) + "\n")


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _probe(folder: Path, what: str, name: str = "probe") -> None:
    """Create and delete a file in ``folder`` named like the temporary file of ``name``: the
    only writability test that holds for root and read-only file systems alike (and that
    meets a name too long before the work)."""
    probe = temp_path(folder / name)
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UserError(f"cannot write {what}: {exc.strerror or exc}") from None


def _not_an_input(out: Path, inputs: Iterable[str | os.PathLike[str] | None]) -> None:
    for inp in inputs:
        if inp is None:
            continue
        ip = Path(inp)
        if _same_file(out, ip) or out.resolve() == ip.resolve():
            raise UserError(f"--out {out} is also an input ({inp}): choose another output")


def check_output_file(
    path: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str] | None] = ()
) -> Path:
    """Check that ``path`` can be written as a file and is none of ``inputs``; one-line
    :class:`UserError` otherwise. Nothing is created but a probe file, deleted at once."""
    out = Path(path)
    if out.is_dir() or str(path).endswith(("/", os.sep)):
        raise UserError(f"cannot write {path}: it is a folder (give a file name)")
    _not_an_input(out, inputs)
    if is_special(out):
        try:
            open(out, "ab").close()
        except OSError as exc:
            raise UserError(f"cannot write {out}: {exc.strerror or exc}") from None
        return out
    folder = out.parent
    if not folder.exists():
        raise UserError(f"cannot write {out}: folder {folder} does not exist")
    if not folder.is_dir():
        raise UserError(f"cannot write {out}: {folder} is not a folder")
    _probe(folder, str(out), out.name)
    return out


def check_output_dir(
    path: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str] | None] = ()
) -> Path:
    """Create folder ``path`` (with parents) if needed and check it can be written and is none
    of ``inputs``; one-line :class:`UserError` otherwise."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise UserError(f"cannot write into {out}: it exists and is not a folder")
    _not_an_input(out, inputs)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create folder {out}: {exc.strerror or exc}") from None
    _probe(out, f"into {out}")
    return out

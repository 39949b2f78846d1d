"""The project's documents stand on their own (issue 32, item 5).

Code and documents cite the design as ``docs/design.md, 3.4``: every such citation must name
a section that docs/design.md has. Nothing may cite the development-only design notes the
project grew from (``DESIGN 3.4``) or another file outside the repository (a path into the
development folders beside it, or on the development machine). Data files beside the
repository are allowed only where tests and experiments look for the public datasets; the
product (``fgslam``, ``factors``, ``devices``, the configuration) and every document never
name them.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DESIGN_DOC = "docs/design.md"
SUFFIXES = (".py", ".md", ".toml")
# this file spells the patterns it looks for
SELF = Path(__file__).resolve().relative_to(ROOT).as_posix()

# files that other work is rewriting and that still hold what a rule forbids: rule -> paths.
# A listed file that no longer breaks the rule fails the test (take it off the list).
PENDING: dict[str, set[str]] = {
    "old-design-citation": set(),
    "outside-document": set(),
    "development-data": set(),
}

SECTION_REF = r"\d+[a-z]?(?:\.\d+)?"
HEADING = re.compile(rf"^#{{2,3}}\s+({SECTION_REF})\.?\s", re.MULTILINE)
CITATION = re.compile(
    rf"docs/design\.md`?(?P<comma>,?)[ \t]*§?[ \t]*"
    rf"(?P<refs>{SECTION_REF}(?:[ \t]*(?:-|,|and)[ \t]*{SECTION_REF})*)?(?![\w.])"
)
# "DESIGN 3.4", also broken over a line ("DESIGN\n    # 3.4") or with a section sign
OLD_CITATION = re.compile(r"\bDESIGN\b(?!\.)[\s#*§]*\d")
# documents outside the repository: the development notes, references and data README,
# anything on the development machine
OUTSIDE_DOCUMENT = re.compile(
    r"\bDESIGN\.md\b|shared/(?:reference|paper)\b|shared/data/README|(?<![\w.])/work/"
)
# the development data folder beside the repository
DEVELOPMENT_DATA = re.compile(r"\.\./shared\b|\bshared/data\b")


def project_files() -> list[str]:
    """The repository's .py, .md and .toml files (tracked, or new and not ignored), as
    posix paths relative to the root; without git, every such file outside hidden and build
    folders."""
    try:
        out = subprocess.run(
            ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
            cwd=ROOT,
            capture_output=True,
            check=True,
        ).stdout.decode()
        names = [n for n in out.split("\0") if n]
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", ".venv", "venv", "build", "dist", "__pycache__"}
        names = [
            p.relative_to(ROOT).as_posix()
            for p in ROOT.rglob("*")
            if not skip.intersection(p.relative_to(ROOT).parts)
            and not any(part.endswith(".egg-info") for part in p.parts)
        ]
    return sorted(
        n for n in set(names) if n.endswith(SUFFIXES) and n != SELF and (ROOT / n).is_file()
    )


def design_sections(text: str) -> set[str]:
    """Section numbers of the design document's headings ("## 5b. ...", "### 3.4 ...")."""
    numbers = HEADING.findall(text)
    duplicates = sorted({n for n in numbers if numbers.count(n) > 1})
    assert not duplicates, f"{DESIGN_DOC}: sections numbered twice: {duplicates}"
    return set(numbers)


def bad_design_citations(text: str, sections: set[str]) -> list[str]:
    """The citations of docs/design.md in ``text`` that name no section or one it lacks."""
    bad = []
    for m in CITATION.finditer(text):
        refs = m.group("refs")
        if refs is None:
            if m.group("comma"):
                bad.append(f"{m.group(0)!r}: names no section")
            continue
        missing = [r for r in re.findall(SECTION_REF, refs) if r not in sections]
        if missing:
            bad.append(f"{m.group(0)!r}: no section {', '.join(missing)}")
    return bad


def is_product(path: str) -> bool:
    """Documents and the product itself, where no development path may appear at all."""
    return path.endswith((".md", ".toml")) or path.startswith(("fgslam/", "factors/", "devices/"))


def violations(path: str, text: str) -> dict[str, list[str]]:
    """Offending lines of ``text`` (the file ``path``) by rule."""
    rules = {"old-design-citation": OLD_CITATION, "outside-document": OUTSIDE_DOCUMENT}
    if is_product(path):
        rules["development-data"] = DEVELOPMENT_DATA
    out: dict[str, list[str]] = {}
    for rule, pattern in rules.items():
        for m in pattern.finditer(text):
            line = text.count("\n", 0, m.start()) + 1
            out.setdefault(rule, []).append(f"{path}:{line}: {m.group(0).strip()!r}")
    return out


def _files_by_rule() -> dict[str, dict[str, list[str]]]:
    found: dict[str, dict[str, list[str]]] = {rule: {} for rule in PENDING}
    for path in project_files():
        text = (ROOT / path).read_text(encoding="utf-8", errors="replace")
        for rule, hits in violations(path, text).items():
            found[rule][path] = hits
    return found


@pytest.mark.parametrize("rule", sorted(PENDING))
def test_no_citation_outside_the_repository(rule):
    """No file cites the development design notes or another file outside the repository
    (rule ``old-design-citation``: "DESIGN 3.4"; ``outside-document``; ``development-data``:
    the data folder beside the repository, in the product and the documents)."""
    found = _files_by_rule()[rule]
    unexpected = {p: h for p, h in found.items() if p not in PENDING[rule]}
    assert not unexpected, "\n".join(h for hits in unexpected.values() for h in hits)
    fixed = sorted(p for p in PENDING[rule] if p not in found)
    assert not fixed, f"no longer break {rule!r}: take them off PENDING: {fixed}"
    if found:
        pytest.xfail(f"still pending ({rule}): {sorted(found)}")


def design_citation_problems() -> list[str]:
    """The citations of docs/design.md in the project's files that name no section of it."""
    sections = design_sections((ROOT / DESIGN_DOC).read_text(encoding="utf-8"))
    bad = []
    for path in project_files():
        text = (ROOT / path).read_text(encoding="utf-8", errors="replace")
        bad += [f"{path}: {b}" for b in bad_design_citations(text, sections)]
    return bad


def test_design_citations_name_existing_sections():
    """Every "docs/design.md, N" in the repository names a section of docs/design.md, which
    keeps the section numbers the code has cited since the notes it replaces."""
    sections = design_sections((ROOT / DESIGN_DOC).read_text(encoding="utf-8"))
    numbered = {"1", "2", "3", "4", "5", "5b", "6", "7", "8", "9"}
    assert numbered | {f"3.{i}" for i in range(1, 8)} <= sections, sorted(sections)
    bad = design_citation_problems()
    assert not bad, "\n".join(bad)


def test_the_checks_catch_planted_citations():
    """The rules above fail on what they are meant to catch (and pass what they allow)."""
    sections = {"1", "3.4", "5", "5b"}
    ok = "(docs/design.md, 3.4), docs/design.md, 5b; `docs/design.md` and docs/design.md 1-5"
    assert bad_design_citations(ok, sections) == []
    for planted in ("(docs/design.md, 3.9)", "docs/design.md, 5c:", "(docs/design.md, 1, 7)"):
        assert bad_design_citations(planted, sections), planted
    assert bad_design_citations("see docs/design.md, section four", sections)

    old = "DES" + "IGN"
    for planted in (f"({old} 3.4)", f"{old}\n    # 6)", f"{old} §5b"):
        assert "old-design-citation" in violations("fgslam/x.py", planted), planted
    found = violations("fgslam/x.py", f"the {old}.md notes, a {old} decision")
    assert list(found) == ["outside-document"] and len(found["outside-document"]) == 1

    shared, work = "../" + "shared", "/" + "work" + "/"
    for planted in (f"{shared}/reference/sick.md", f"{shared}/data/README.md", f"{work}tmp/x"):
        assert "outside-document" in violations("tests/test_x.py", planted), planted
    data = f"{shared}/data/intel-corrected.log.gz"
    assert violations("tests/test_x.py", data) == {}
    assert violations("experiments/x.py", data) == {}
    for path in ("fgslam/x.py", "docs/x.md", "README.md", "pyproject.toml"):
        assert "development-data" in violations(path, data), path


def test_a_planted_citation_in_a_file_fails(tmp_path, monkeypatch):
    """End to end: a citation planted in a project file is found by the file scan."""
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "design.md").write_text("# Design\n\n## 1. Shape\n", encoding="utf-8")
    (tmp_path / "fgslam").mkdir()
    (tmp_path / "fgslam" / "a.py").write_text(
        '"""Model (' + "DES" + 'IGN 3.4; docs/design.md, 2)."""\n', encoding="utf-8"
    )
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    found = _files_by_rule()
    assert list(found["old-design-citation"]) == ["fgslam/a.py"]
    assert design_citation_problems() == ["fgslam/a.py: 'docs/design.md, 2': no section 2"]

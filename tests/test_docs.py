"""The documents the code and docs cite are in the repository, and the cited parts of them exist.

- Every ``something.md`` named in render_core/, service/, proto/, tests/, docs/ or README.md is a file of this
  repository (found from the repository root or from the citing file's folder; nothing outside the checkout).
- Every citation of the method page ("docs/method.md section 9", "sections 3-6", "sections 5 to 7",
  "section 9, steps 1-3", ...) names a ``## N.`` heading of docs/method.md, and a cited step is a numbered item
  of that section. Inside docs/method.md itself a bare "section N" is checked the same way.
- A quoted part of a document ('docs/architecture.md, "Avatar bundle"') is one of its headings.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
METHOD = ROOT / "docs" / "method.md"
SCANNED_DIRS = ("render_core", "service", "proto", "tests", "docs")
SCANNED_FILES = ("README.md",)
TEXT_SUFFIXES = {".py", ".md", ".proto", ".cpp", ".hpp", ".h", ".inl", ".txt", ".sh", ".html", ".toml", ".cfg",
                 ".json", ".yaml", ".yml"}
SKIP_DIRS = {"__pycache__", "build", ".pytest_cache", ".ruff_cache"}
THIS = Path(__file__).resolve()  # its docstring quotes citations as examples

DOC_REF = re.compile(r"(?<![\w./-])((?:[\w.-]+/)*[\w.-]+\.md)\b")
NUMBERS = r"\d+(?:\s*(?:-|\u2013|to|and|or|,)\s*\d+)*"
CITATION = re.compile(rf"(?<![\w/.-])(?:docs/)?method\.md[\s,:]*\(?\s*[Ss]ections?\s+(?P<sections>{NUMBERS})"
                      rf"(?P<steps>,?\s*steps?\s+(?P<step_numbers>{NUMBERS}))?")
SELF_CITATION = re.compile(rf"\b[Ss]ections?\s+(?P<sections>{NUMBERS})"
                           rf"(?P<steps>,?\s*steps?\s+(?P<step_numbers>{NUMBERS}))?")
QUOTED_PART = re.compile(r"(?<![\w./-])((?:[\w.-]+/)*[\w.-]+\.md),\s*\"([^\"\n]{1,80})\"")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*$", re.M)
SECTION_HEADING = re.compile(r"^## (\d+)\. \S", re.M)
NUMBERED_ITEM = re.compile(r"^\s*(\d+)\.\s", re.M)


def scanned_files() -> list[Path]:
    files = [ROOT / name for name in SCANNED_FILES if (ROOT / name).is_file()]
    for top in SCANNED_DIRS:
        for path in sorted((ROOT / top).rglob("*")):
            if SKIP_DIRS.intersection(path.relative_to(ROOT).parts) or not path.is_file():
                continue
            if path.suffix in TEXT_SUFFIXES and path.resolve() != THIS:
                files.append(path)
    return files


def read(path: Path) -> str:
    return path.read_text(encoding="utf-8", errors="replace")


def joined(text: str) -> str:
    """Lines joined into one, dropping indentation and comment markers, so citations wrapped over lines match."""
    return re.sub(r"[ \t]*\n[ \t]*(?:(?:#|//|\*)[ \t]*)?", " ", text)


def numbers(spec: str) -> set[int]:
    """'3-6' -> {3, 4, 5, 6}; '5 to 7' -> {5, 6, 7}; '8 and 11' -> {8, 11}; '1, 2 and 4' -> {1, 2, 4}."""
    out: set[int] = set()
    for part in re.split(r"\s*(?:,|\band\b|\bor\b)\s*", spec.strip()):
        if not part:
            continue
        bounds = [int(n) for n in re.split(r"\s*(?:-|\u2013|\bto\b)\s*", part)]
        out.update(range(bounds[0], bounds[-1] + 1))
    return out


def method_sections(text: str) -> dict[int, str]:
    """Section number -> that section's text (from its ``## N.`` heading to the next ``## `` heading)."""
    starts = [(int(m.group(1)), m.start()) for m in SECTION_HEADING.finditer(text)]
    out = {}
    for i, (number, start) in enumerate(starts):
        following = re.search(r"^## ", text[start + 3:], re.M)
        out[number] = text[start:start + 3 + following.start()] if following else text[start:]
        assert i == 0 or starts[i - 1][0] < number
    return out


def resolve(ref: str, citing: Path) -> Path | None:
    """The repository file ``ref`` names, from the root or from the citing file's folder (None: not in the repo)."""
    for base in (ROOT, citing.parent):
        candidate = (base / ref).resolve()
        if candidate.is_file() and candidate.is_relative_to(ROOT):
            return candidate
    return None


def test_cited_documents_exist():
    missing = []
    for path in scanned_files():
        for ref in sorted(set(DOC_REF.findall(read(path)))):
            if resolve(ref, path) is None:
                missing.append(f"{path.relative_to(ROOT)} cites {ref}, which is not a file of this repository")
    assert not missing, "\n".join(missing)


def test_method_page_is_numbered():
    assert METHOD.is_file(), "docs/method.md is missing"
    found = [int(n) for n in SECTION_HEADING.findall(read(METHOD))]
    assert found == list(range(1, len(found) + 1)), f"docs/method.md's sections must be numbered 1, 2, ...: {found}"
    assert len(found) >= 11, f"docs/method.md has {len(found)} numbered sections, the code cites 11"


def test_method_citations_name_real_sections():
    assert METHOD.is_file(), "docs/method.md is missing"
    sections = method_sections(read(METHOD))
    problems, count = [], 0
    for path in scanned_files():
        text = joined(read(path))
        pattern = SELF_CITATION if path.resolve() == METHOD.resolve() else CITATION
        for m in pattern.finditer(text):
            count += 1
            where = f"{path.relative_to(ROOT)}: {m.group(0)!r}"
            cited = numbers(m.group("sections"))
            absent = sorted(n for n in cited if n not in sections)
            if absent:
                problems.append(f"{where}: docs/method.md has no section {absent}")
                continue
            if m.group("step_numbers"):
                if len(cited) != 1:
                    problems.append(f"{where}: steps of more than one section")
                    continue
                (number,) = cited
                items = {int(n) for n in NUMBERED_ITEM.findall(sections[number])}
                steps = sorted(numbers(m.group("step_numbers")) - items)
                if steps:
                    problems.append(f"{where}: section {number} has no numbered step {steps}")
    assert count > 0, "no citation of docs/method.md found: the pattern no longer matches the code's citations"
    assert not problems, "\n".join(problems)


def test_quoted_parts_are_headings():
    problems = []
    for path in scanned_files():
        for ref, title in QUOTED_PART.findall(joined(read(path))):
            target = resolve(ref, path)
            if target is None:
                continue  # reported by test_cited_documents_exist
            headings = [h for _, h in HEADING.findall(read(target))]
            if not any(title.lower() in h.lower() for h in headings):
                problems.append(f"{path.relative_to(ROOT)} cites {ref}, \"{title}\", which is not a heading there")
    assert not problems, "\n".join(problems)


def test_the_checks_catch_what_they_should(tmp_path):
    """The patterns on the citation forms the code uses, and a missing section or step is caught."""
    text = joined("see docs/method.md section\n    # 9, steps 1-3 and (docs/method.md sections 5 to 7); also\n"
                  "docs/method.md sections 3-6, docs/method.md sections 8 and 11, method.md section 2 step 6")
    found = [(numbers(m.group("sections")), m.group("step_numbers")) for m in CITATION.finditer(text)]
    assert found == [({9}, "1-3"), ({5, 6, 7}, None), ({3, 4, 5, 6}, None), ({8, 11}, None), ({2}, "6")]
    sections = method_sections("# t\n\n## 1. One\n1. a\n2. b\n\n## 2. Two\ntext\n")
    assert set(sections) == {1, 2}
    assert {int(n) for n in NUMBERED_ITEM.findall(sections[1])} == {1, 2}
    assert not NUMBERED_ITEM.findall(sections[2])
    assert DOC_REF.findall("a docs/x.md, ../shared/y.md and https://example.org/README.md") == [
        "docs/x.md", "../shared/y.md"]
    assert resolve("../shared/y.md", ROOT / "README.md") is None

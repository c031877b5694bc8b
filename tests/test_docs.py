"""The repository explains itself: every document it points at is in it."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TEXT = [
    p
    for folder in ("mrcert", "conf", "tests", "benchmarks", "docs", ".ci")
    for p in (ROOT / folder).rglob("*")
    if p.is_file() and p.suffix in ("", ".py", ".yaml", ".md", ".txt")
] + [ROOT / "README.md", ROOT / "Makefile", ROOT / "pyproject.toml"]
SECTIONS = set(re.findall(r"^## (§\d+)", (ROOT / "docs" / "method.md").read_text(), flags=re.M))


def references(pattern: str, suffixes: tuple[str, ...] = ()):
    for path in TEXT:
        if suffixes and path.suffix not in suffixes:
            continue
        for match in re.finditer(pattern, path.read_text(errors="replace")):
            yield path.relative_to(ROOT), match


def test_every_referenced_document_exists():
    missing = [
        (str(where), m.group(1)) for where, m in references(r"(docs/[\w./-]*\w)") if not (ROOT / m.group(1)).exists()
    ]
    links = [
        (str(where), m.group(1))
        for where, m in references(r"\]\((?!https?:|#)([^)\s]+)\)", (".md",))
        if not (ROOT / where).parent.joinpath(m.group(1)).exists()
    ]
    assert missing == [] and links == []


def test_method_sections_cited_by_the_code_exist_and_nothing_points_outside():
    cited = {(str(where), m.group(1)) for where, m in references(r"method\.md (§\d+)")}
    assert cited and {c for c in cited if c[1] not in SECTIONS} == set()
    outside = [str(where) for where, _ in references(r"\bSPEC\b|\.\./shared") if where.name != "test_docs.py"]
    assert outside == []

"""The repository explains itself: every document it points at is in it."""

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TEXT = [
    p
    for folder in ("mrcert", "conf", "tests", "benchmarks", "docs", ".ci")
    for p in (ROOT / folder).rglob("*")
    if p.is_file()
    and p.suffix in ("", ".py", ".yaml", ".md", ".txt")
    and not p.is_relative_to(ROOT / "docs" / "results_store")  # runs' records (configs, logs), not text of ours
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


# How, when or on which borrowed machine the work was done, or which work item asked for it:
# the repository describes the product, and a figure names only the machine it was measured on.
DEVELOPMENT = re.compile(
    r"""
    \b20\d\d-[01]\d-[0-3]\d\b                       # a date of work
    | \bsessions?\b | \bsittings?\b                  # when
    | \b(?:lent|borrowed)\b                          # whose machine
    | \bscratch\ (?:copy|store|folder|clone)\b | <scratch>
    | \b(?:issue|work\ item|ticket|stop)\ ?\#?\d+    # which piece of work asked for it
    | \bin\ pieces\b | \bwas\ replaced\b | \bcould\ not\ be\ carried\b
    | \b(?:this|that)\ (?:morning|afternoon|evening)\b | \bat\ the\ time\b
    """,
    re.I | re.X,
)
PRODUCT = [p for p in TEXT if p.suffix in ("", ".py", ".yaml", ".md") and p.parent.name != ".ci"]


def development_lines(paths, root: Path = ROOT) -> list[str]:
    found = []
    for path in paths:
        if path.name == "test_docs.py":
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if DEVELOPMENT.search(line):
                found.append(f"{path.relative_to(root)}:{number}: {line.strip()}")
    return found


def test_the_repository_describes_the_product_not_how_or_when_it_was_built():
    assert development_lines(PRODUCT) == []


def test_the_development_vocabulary_check_catches_what_it_names(tmp_path):
    caught = [  # made-up examples of each kind the check names
        "measured on 1999-12-31 on a borrowed laptop",
        "in a scratch copy of the code",
        '"""Ticket 7: no room for the store."""',
        "the second sitting's run",
        "in pieces, because the machine was replaced",
    ]
    kept = ["ResNet-18 from scratch, 20 classes", "one NVIDIA H100", "outputs/runs/<task>/<date>_<time>_<id>/"]
    page = tmp_path / "page.md"
    page.write_text("\n".join(caught + kept))
    assert [line.split(": ", 1)[1] for line in development_lines([page], tmp_path)] == caught


def page_table(page: str, heading: str) -> list[list[str]]:
    """The rows of the first Markdown table under ``## heading`` of a page (cells stripped)."""
    section = page.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("|")]
    return [[c.strip() for c in row.strip("|").split("|")] for row in rows[2:]]


def test_the_readme_quotes_the_evidence_page_exactly():
    """Every figure of the README that comes from the reproduction's runs is the page's: the key
    table (certified accuracy at r = sigma, ours and the paper's) and what the README reads from it,
    the paper's third finding, the base models' test range, the paper's base range and the
    reproduction's run time."""
    readme, page = (ROOT / "README.md").read_text(), (ROOT / "docs" / "results.md").read_text()
    prose = " ".join(readme.split())
    certified = {}
    for row in page_table(page, "Table 3, ours (paper)"):
        axis, variant = row[0].lower(), row[1].split()[1].lower()
        certified[(axis, variant)] = row[4]
    key = re.search(r"\| axis \|[^\n]*\n\|[-| ]+\|\n((?:\|[^\n]*\n)+)", readme)
    quoted = {}
    for line in key.group(1).splitlines():
        axis, vanilla, augmented = (c.strip() for c in line.strip("|").split("|"))
        quoted[(axis, "vanilla")], quoted[(axis, "augmented")] = vanilla, augmented
    assert quoted == certified and len(quoted) == 12
    ours = {key: float(cell.split(" (")[0]) for key, cell in certified.items()}
    axes = list(dict.fromkeys(axis for axis, _ in ours))
    raised = [a for a in axes if ours[(a, "augmented")] > ours[(a, "vanilla")]]
    named = ", ".join(raised[:-1]) + " and " + raised[-1] if len(raised) > 1 else "".join(raised) or "none"
    assert f"motion augmentation raises it on {named} ({len(raised)} of 6 axes)" in prose
    weakest = min(ours, key=ours.get)[0]
    assert f"{weakest} is where our models are least robust" in prose
    held = re.search(r"empirical robust accuracy\*\*: holds in (all 12|\d+ of 12)", page).group(1)
    assert f"at most the smoothed model's empirical robust accuracy in {held} rows" in prose
    tests = [float(r[2]) for r in page_table(page, "The base models")]
    assert f"{min(tests):.2f}-{max(tests):.2f} on the 120 test views" in prose
    paper = re.search(r"the paper's base ResNet-18 models: (\d\.\d+) to (\d\.\d+)", page).groups()
    assert f"(the paper's base ResNet-18s: {paper[0]}-{paper[1]})" in prose
    hours = float(next(r for r in page_table(page, "Time per stage") if r[0] == "every stage")[4])
    assert f"{hours:.1f} hours of run time on 2 CPU cores" in prose


def test_docs_tasks_names_every_task_group_option_and_task_setting():
    """docs/tasks.md against the task registry and conf/: a row per task, every option of every
    config group a user picks, and every setting of every task (as ``task.<key>``)."""
    import yaml

    from mrcert.infra.tasks import TASKS

    doc = (ROOT / "docs" / "tasks.md").read_text()
    assert [t for t in TASKS if f"| `{t}` |" not in doc] == []
    conf = ROOT / "conf"
    groups = [g for g in conf.iterdir() if g.is_dir() and g.name not in ("hydra", "task")]
    options = [f"{g.name}={p.stem}" for g in groups for p in g.glob("*.yaml")]
    assert [o for o in options if f"`{o.split('=')[1]}`" not in doc and o not in doc] == []
    settings = []
    for path in (conf / "task").rglob("*.yaml"):  # with the evaluation tasks' shared settings
        keys = yaml.safe_load(path.read_text()) or {}
        settings += [f"task.{k}" for k in keys if k not in ("defaults", "name", "_target_")]
    assert sorted({s for s in settings if s not in doc}) == []


def test_every_patch_on_a_study_page_applies_to_the_shipped_code(tmp_path):
    """A study's variant that is not a setting is stated as a patch: each ```diff block on a
    study page applies cleanly to this tree (``git apply --check``), so its command reruns it."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    blocks = [
        (page.name, block)
        for page in sorted((ROOT / "docs" / "studies").glob("*.md"))
        for block in re.findall(r"```diff\n(.*?)```", page.read_text(), flags=re.S)
    ]
    assert len(blocks) >= 3
    for i, (page, block) in enumerate(blocks):
        patch = tmp_path / f"{i}.patch"
        patch.write_text(block)
        check = subprocess.run(["git", "apply", "--check", str(patch)], cwd=ROOT, capture_output=True, text=True)
        assert check.returncode == 0, f"{page}: {check.stderr}"

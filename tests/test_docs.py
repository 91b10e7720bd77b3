"""The documentation says what the code is: the generated benchmark page matches the stored results,
the architecture page lists every module, the README stays a manual (size, line length, no history)."""
from __future__ import annotations

import importlib.util
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _report_module():
    spec = importlib.util.spec_from_file_location("benchmarks_report", ROOT / "benchmarks" / "report.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_benchmarks_page_is_generated_from_the_stored_results():
    report = _report_module()
    page = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    assert page == report.render(), "docs/benchmarks.md is out of date: run python benchmarks/report.py"


def test_benchmarks_page_cites_each_result_with_its_command():
    """Every section names the JSON it reads and the command that writes it."""
    page = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    for name in ("bvp_testset.json", "estimation_vs_casadi.json", "mixture_vs_casadi.json",
                 "command_vs_casadi.json", "long_records.json", "figures.json", "gpu.json", "diagnosis.json"):
        if (ROOT / "benchmarks" / "results" / name).exists():
            assert f"benchmarks/results/{name}" in page, name
    sections = page.split("\n## ")[1:]
    assert sections and all("```bash\npython " in s for s in sections)


def test_benchmarks_page_formats():
    report = _report_module()
    assert report.sec(0.0123) == "12.3 ms" and report.sec(2.345) == "2.35 s" and report.sec(None) == "–"
    assert report.geomean([1.0, 4.0]) == 2.0
    assert report.newton_names("press + tolerance continuation, musn, MUSN's") == \
        "armijo + tolerance continuation, appendix_a, MUSN's"
    assert report.table(["a", "b"], [[1, 2]]) == ["| a | b |", "|---|---|", "| 1 | 2 |", ""]


def _modules() -> list[str]:
    return sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "shootlab").rglob("*.py"))


def test_architecture_lists_every_module():
    page = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    listed = set(re.findall(r"`(shootlab/[\w/]+\.py)`", page))
    missing = [m for m in _modules() if m not in listed]
    assert not missing, f"docs/architecture.md does not list {missing}"
    gone = sorted(m for m in listed if not (ROOT / m).exists())
    assert not gone, f"docs/architecture.md lists modules that do not exist: {gone}"


def _prose_lines(text: str):
    code = False
    for number, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            code = not code
            continue
        if not code:
            yield number, line


def test_readme_is_a_manual():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.encode("utf-8")) <= 40_000
    long = [n for n, line in _prose_lines(text) if len(line) > 700]
    assert not long, f"README.md lines over 700 characters outside code blocks: {long}"
    for doc in ("docs/architecture.md", "docs/benchmarks.md", "docs/design.md", "docs/diagnosis.md",
                "docs/your_own_model.md", "CHANGELOG.md"):
        assert doc in text and (ROOT / doc).exists(), doc


HISTORY = re.compile(r"this session|\b(first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|"
                     r"previous|earlier|last|next) session\b|\bissue \d+|filing code|\bformerly\b", re.IGNORECASE)


def test_no_history_wording_in_the_manuals_and_the_code():
    """What the code does, not how it came to be: the history is CHANGELOG.md's."""
    files = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "shootlab").rglob("*.py"))]
    hits = [f"{f.relative_to(ROOT)}:{n}: {line.strip()[:80]}" for f in files
            for n, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1) if HISTORY.search(line)]
    assert not hits, "history wording:\n" + "\n".join(hits)

"""Every link in the Markdown files resolves: relative links and images point at files that exist, `#anchors` at
headings that exist, and repository paths written in backticks in the hand-written docs exist. Reports and other
generated Markdown are checked for links only: their commands record what ran, at the commit that ran them."""
from __future__ import annotations

import os
import re
import subprocess
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SKIP_DIRS = {".git", ".venv", "runs", "node_modules", "build"}
# written by a program (mcrl report, the study's compare and summary): links checked, backtick paths not
GENERATED = re.compile(r"(^|/)(report/report\.md|sweep-fetchreach/report\.md|docs/studies/sb3-parity/.*)$")
TOP = ("src/", "docs/", "tests/", "benchmarks/", "scripts/", "studies/")

LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
CODE = re.compile(r"`([^`\n]+)`")
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.M)


def markdown_files() -> list[Path]:
    out = []
    for p in ROOT.rglob("*.md"):
        rel = p.relative_to(ROOT)
        if not SKIP_DIRS.intersection(rel.parts[:-1]):
            out.append(p)
    return sorted(out)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped (but - and _), spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text
    text = re.sub(r"[^\w\- ]", "", text.replace("`", "").lower())
    return text.replace(" ", "-")


def anchors(path: Path, cache: dict[Path, set[str]]) -> set[str]:
    if path not in cache:
        seen: dict[str, int] = {}
        found = set()
        for h in HEADING.findall(FENCE.sub("", path.read_text(errors="replace"))):
            s = slug(h)
            n = seen.get(s, 0)
            found.add(s if n == 0 else f"{s}-{n}")
            seen[s] = n + 1
        cache[path] = found
    return cache[path]


def broken_links(path: Path, cache: dict[Path, set[str]]) -> list[str]:
    text = FENCE.sub("", path.read_text(errors="replace"))
    bad = []
    for target in LINK.findall(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        file, _, frag = target.partition("#")
        dest = path if not file else (path.parent / file).resolve()
        if not dest.exists():
            bad.append(f"{target} (no such file)")
        elif frag and dest.suffix == ".md" and frag not in anchors(dest, cache):
            bad.append(f"{target} (no heading #{frag})")
    return bad


def git_ignored(paths: list[str]) -> set[str]:
    """The paths git ignores and does not track: they exist in this checkout only (a built venv, fetched wheels),
    never in a fresh clone, so a doc must not name them as if they were there."""
    if not paths or not (ROOT / ".git").exists():
        return set()
    out = subprocess.run(["git", "check-ignore", "--stdin"], cwd=ROOT, input="\n".join(paths), text=True,
                         capture_output=True)
    return set(out.stdout.split())


def broken_paths(path: Path) -> list[str]:
    """Repository paths in inline code (`docs/x.md`, `python scripts/y.py ...`) that a fresh clone lacks (missing
    or git-ignored); placeholders (RUN_DIR, <name>, *, {a,b}, $VAR) and paths under a run's directory are not
    checked."""
    text = FENCE.sub("", path.read_text(errors="replace"))
    bad, present = [], []
    for span in CODE.findall(text):
        for token in span.split():
            token = token.strip("'\",;()[]").split(":")[0].rstrip(".")
            if not token.startswith(TOP):
                continue
            if (ROOT / token).exists():
                present.append(token)
            elif not re.search(r"[<>*{}$]|\.\.\.|(^|/)[A-Z][A-Z0-9_]*(/|$)", token):  # not a placeholder
                bad.append(token)
    return bad + sorted(git_ignored(present))


def test_every_link_and_path_in_the_markdown_resolves():
    cache: dict[Path, set[str]] = {}
    problems = {}
    for p in markdown_files():
        rel = p.relative_to(ROOT).as_posix()
        bad = broken_links(p, cache)
        if not GENERATED.search(rel) and rel != "CHANGELOG.md":  # the changelog names files as they were then
            bad += [f"`{t}` (no such path)" for t in broken_paths(p)]
        if bad:
            problems[rel] = bad
    assert not problems, problems


def test_the_checker_sees_a_broken_link(tmp_path):
    doc = tmp_path / "a.md"
    doc.write_text("# Top\n\n## Two words (`x`)\n\n[ok](#two-words-x) [gone](b.md) [bad](#nothing) "
                   "[self](a.md#top)\n\n```\n[in a fence](c.md)\n```\n")
    assert broken_links(doc, {}) == ["b.md (no such file)", "#nothing (no heading #nothing)"]
    assert slug("A grid as one computation (`--backend vmap`)") == "a-grid-as-one-computation---backend-vmap"
    assert slug("A sweep's workers and their cores") == "a-sweeps-workers-and-their-cores"


def test_a_path_only_this_checkout_has_counts_as_missing(tmp_path):
    """A git-ignored file exists here but not in CI's fresh clone: naming it in a doc is a broken path."""
    cache_dir = ROOT / "tests" / "__pycache__"
    cache_dir.mkdir(exist_ok=True)
    fd, name = tempfile.mkstemp(suffix=".pyc", dir=cache_dir)
    os.close(fd)
    built = Path(name)
    try:
        rel = built.relative_to(ROOT).as_posix()
        doc = tmp_path / "a.md"
        doc.write_text(f"Run `{rel}` and `tests/test_docs_links.py`, not `tests/no_such_file.py`.\n")
        assert broken_paths(doc) == ["tests/no_such_file.py", rel]
    finally:
        built.unlink()

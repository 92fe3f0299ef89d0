#!/usr/bin/env python3
"""Checks the relative links of the project's Markdown files (ctest Docs.Links, label docs).

Every relative link or image in a committed .md file (README.md, docs/*.md, the folders' READMEs) must
name a file or folder that exists, resolved from the linking file's folder; a #fragment pointing at a
Markdown file (or at the same file) must name one of its headings, slugged as GitHub renders them.
Absolute URLs (http:, https:, mailto:, ...) are not fetched. Links inside code spans and fenced code
blocks are text, not links.

  check_doc_links.py [REPO_ROOT]     check every .md file git tracks (or, outside git, every .md file
                                     below REPO_ROOT except build*/, .deps, .git, out/)
  check_doc_links.py --self-test     only the checker's own cases

Exit 0 when every link resolves, 1 with one line per broken link (file:line: target: why).
The self-test runs first in both modes, so a checker that stopped finding broken links fails too.
"""
import os
import re
import subprocess
import sys
import tempfile
import unicodedata
from urllib.parse import unquote

FENCE = re.compile(r"^\s{0,3}(`{3,}|~{3,})")
ATX = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
SETEXT = re.compile(r"^\s{0,3}(=+|-+)\s*$")
# [text](target "title") and ![alt](target); the target may be <bracketed>.
INLINE = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*(<[^>]*>|[^()\s]*(?:\([^()\s]*\)[^()\s]*)*)(?:\s+(?:\"[^\"]*\"|'[^']*'|\([^)]*\)))?\s*\)")
REFDEF = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*(<[^>]*>|\S+)")
CODE_SPAN = re.compile(r"(`+)(.+?)\1", re.S)
SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


def strip_code_spans(line):
    """The line with code spans blanked (same length, so columns stay)."""
    return CODE_SPAN.sub(lambda m: " " * len(m.group(0)), line)


def prose_lines(text):
    """(line number, line) of the lines outside fenced code blocks."""
    fence = None
    for number, line in enumerate(text.splitlines(), 1):
        m = FENCE.match(line)
        if m:
            marker = m.group(1)
            if fence is None:
                fence = marker
            elif marker[0] == fence[0] and len(marker) >= len(fence):
                fence = None
            continue
        if fence is None:
            yield number, line


def slug(heading):
    """GitHub's anchor for a heading's text: the rendered text lowercased, punctuation removed
    (letters, digits, '_', '-' and spaces stay), each space a hyphen."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # links and images -> their text
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML tags
    text = text.lower()
    kept = []
    for ch in text:
        cat = unicodedata.category(ch)
        if ch in "-_ " or cat[0] in "LN" or cat == "Mn":
            kept.append(ch)
    return "".join(kept).replace(" ", "-")


def anchors(text):
    """Every heading anchor of a Markdown text, duplicates numbered -1, -2, ... as GitHub does."""
    seen, out = {}, set()
    previous = None
    for _, line in prose_lines(text):
        m = ATX.match(line)
        title = m.group(2) if m else None
        if title is None and previous is not None and previous.strip() and SETEXT.match(line) \
                and not ATX.match(previous) and not previous.lstrip().startswith(("|", "-", "*", ">")):
            title = previous.strip()
        previous = line
        if title is None:
            continue
        base = slug(title)
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(text):
    """(line number, target) of every inline link, image and reference definition outside code."""
    for number, line in prose_lines(text):
        prose = strip_code_spans(line)
        for m in INLINE.finditer(prose):
            yield number, m.group(1)
        m = REFDEF.match(prose)
        if m:
            yield number, m.group(1)


def check_file(path, root, anchor_cache):
    """Problems of one Markdown file, as 'file:line: target: why' strings."""
    with open(path, encoding="utf-8") as f:
        text = f.read()
    rel = os.path.relpath(path, root)
    problems = []
    for number, target in links(text):
        target = target[1:-1] if target.startswith("<") and target.endswith(">") else target
        if not target or SCHEME.match(target):
            continue
        file_part, _, fragment = target.partition("#")
        file_part = unquote(file_part)
        if file_part:
            dest = os.path.normpath(os.path.join(os.path.dirname(path), file_part))
            if not os.path.exists(dest):
                problems.append(f"{rel}:{number}: {target}: no such file ({os.path.relpath(dest, root)})")
                continue
        else:
            dest = path
        if fragment and dest.endswith(".md") and os.path.isfile(dest):
            if dest not in anchor_cache:
                with open(dest, encoding="utf-8") as f:
                    anchor_cache[dest] = anchors(f.read())
            if unquote(fragment).lower() not in anchor_cache[dest]:
                problems.append(f"{rel}:{number}: {target}: no heading with anchor #{fragment} in "
                                f"{os.path.relpath(dest, root)}")
    return problems


def markdown_files(root):
    try:
        out = subprocess.run(["git", "-C", root, "ls-files", "-z", "--", "*.md"], check=True,
                             capture_output=True).stdout.decode()
        files = [os.path.join(root, f) for f in out.split("\0") if f]
        if files:
            return sorted(f for f in files if os.path.isfile(f))
    except (OSError, subprocess.CalledProcessError):
        pass
    skip = re.compile(r"^(build.*|\.deps|\.git|\.carry|out|\.whl)$")
    found = []
    for folder, dirs, names in os.walk(root):
        if folder == root:
            dirs[:] = [d for d in dirs if not skip.match(d)]
        found += [os.path.join(folder, n) for n in names if n.endswith(".md")]
    return sorted(found)


def self_test():
    """The checker's own cases: GitHub slugs, and broken links it must report."""
    failures = []
    slugs = {  # heading text -> the anchor GitHub gives it
        "Quick start": "quick-start",
        "FP8 frozen base (opt-in: `train.fp8_base`)": "fp8-frozen-base-opt-in-trainfp8_base",
        'Inputs mode (`cond_mode = "inputs"`)': "inputs-mode-cond_mode--inputs",
        "Probe outputs (`probe --scene scene.json --out DIR`)": "probe-outputs-probe---scene-scenejson---out-dir",
        "Step caching: speed (`bench_stage1 --step-cache`)": "step-caching-speed-bench_stage1---step-cache",
        "Session of 2026-11-26: the remaining long runs, on more cores":
            "session-of-2026-11-26-the-remaining-long-runs-on-more-cores",
        "**Bold** and [a link](x.md)": "bold-and-a-link",
    }
    for heading, want in slugs.items():
        if slug(heading) != want:
            failures.append(f"slug({heading!r}) = {slug(heading)!r}, GitHub gives {want!r}")
    if anchors("# A\n## A\n## A\n") != {"a", "a-1", "a-2"}:
        failures.append("duplicate headings are not numbered -1, -2")
    with tempfile.TemporaryDirectory() as root:
        os.makedirs(os.path.join(root, "docs"))
        with open(os.path.join(root, "docs", "page.md"), "w") as f:
            f.write("# Page\n\n## Some section\n\nBack to the [README](../README.md#top-section).\n")
        with open(os.path.join(root, "README.md"), "w") as f:
            f.write("# Top section\n\n"
                    "[ok](docs/page.md) [ok](docs/page.md#some-section) [ok](#top-section) [ok](docs/)\n"
                    "![ok](docs/page.md) [ok](https://example.org/missing.md) `[code](missing.md)`\n"
                    "[bad file](docs/missing.md)\n"
                    "[bad anchor](docs/page.md#no-such-section)\n"
                    "[bad local anchor](#nowhere)\n"
                    "```\n[in a fence](missing.md)\n```\n"
                    "[ref]: docs/gone.md\n")
        problems = check_file(os.path.join(root, "README.md"), root, {})
        problems += check_file(os.path.join(root, "docs", "page.md"), root, {})
        want = {"docs/missing.md", "docs/page.md#no-such-section", "#nowhere", "docs/gone.md"}
        got = {p.split(": ")[1] for p in problems}
        if got != want:
            failures.append(f"broken links found {sorted(got)}, expected {sorted(want)}")
    return failures


def main(argv):
    failures = self_test()
    if failures:
        print("check_doc_links self-test failed:", *failures, sep="\n  ")
        return 1
    if argv[1:2] == ["--self-test"]:
        print("check_doc_links self-test: ok")
        return 0
    root = os.path.abspath(argv[1] if len(argv) > 1 else os.path.join(os.path.dirname(__file__), ".."))
    files = markdown_files(root)
    if not files:
        print(f"error: no Markdown files under {root}")
        return 1
    cache, problems, count = {}, [], 0
    for path in files:
        with open(path, encoding="utf-8") as f:
            count += sum(1 for _ in links(f.read()))
        problems += check_file(path, root, cache)
    for p in problems:
        print(p)
    print(f"{len(files)} Markdown files, {count} links, {len(problems)} broken")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
